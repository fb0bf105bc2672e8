"""Preprocessing (Stage 2, step 1): normals of the depth, the masked points, and their grid for the posture graph."""

from __future__ import annotations

import numpy as np
import pytest

from surgtrack.config import PreprocessConfig
from surgtrack.geometry import depth_to_xyz
from surgtrack.io import Frame
from surgtrack.posture_graph import GridPoints
from surgtrack.preprocess import normals_from_planes, preprocess, remasked

K = np.array([[300.0, 0.0, 80.0], [0.0, 300.0, 60.0], [0.0, 0.0, 1.0]])


def tilted_plane(h: int = 120, w: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """Depth of the plane n . x = d seen by K, and its unit normal n (facing the camera)."""
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)
    d = -0.4 * np.linalg.norm([0.3, -0.2, -1.0])  # the plane z = 0.4 + 0.3 x - 0.2 y
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, dtype=float)], -1)
    return (d / (rays @ n)).astype(np.float32), n


def test_normals_of_a_plane_face_the_camera_and_are_zero_at_the_border():
    depth, n = tilted_plane()
    xyz = depth_to_xyz(depth, K).astype(np.float32)
    planes = [np.ascontiguousarray(xyz[..., k]) for k in range(3)]
    for step in (1, 2):
        nrm = np.stack(normals_from_planes(*planes, step), axis=-1)
        inner = nrm[step:-step, step:-step]
        assert np.abs(inner - n.astype(np.float32)).max() < 1e-4
        assert not nrm[:step].any() and not nrm[:, -step:].any()
    flat = np.zeros(depth.shape, np.float32)  # no depth: no normal, and nothing undefined
    assert not np.any(normals_from_planes(flat, flat, flat))


def test_grid_keeps_the_valid_points_and_the_graph_finds_them():
    depth, n = tilted_plane()
    mask = np.zeros(depth.shape, bool)
    mask[30:90, 40:120] = True
    depth[50:54, 60:64] = 0.0  # a hole in the depth
    frame = Frame(0, "0", np.zeros(depth.shape + (3,), np.uint8), depth, K, mask)
    obs = preprocess(frame, mask, PreprocessConfig())
    xyz, nrm, Kg = obs.grid(2)
    assert xyz.shape == (60, 80, 3) and np.allclose(Kg[:2], K[:2] / 2)
    on = obs.valid[::2, ::2]
    assert on.sum() > 500 and not on[26, 31]  # the hole is not valid
    assert np.array_equal(xyz[on], obs.xyz[::2, ::2][on]) and not xyz[~on].any() and not nrm[~on].any()
    g = GridPoints.of(xyz, nrm)
    assert np.array_equal(g.idx, np.flatnonzero(on))
    assert np.allclose(g.p, xyz[on]) and np.allclose(np.linalg.norm(g.q, axis=1), 1.0)
    v, u = np.divmod(g.idx, 80)
    away = (np.abs(2 * v - 52) > 8) | (np.abs(2 * u - 62) > 8)  # the filter bends the depth at the hole's edge
    assert np.allclose(g.q[away], n, atol=1e-3)
    top, left, h, w = g.box
    assert (top, left, h, w) == (v.min(), u.min(), v.max() - v.min() + 1, u.max() - u.min() + 1)
    lut = g.lut.reshape(h, w)
    assert np.array_equal(lut[v - top, u - left], np.arange(1, len(g.idx) + 1))
    assert not lut[~on[top : top + h, left : left + w]].any()


def test_observation_held_in_its_crop_reads_as_the_whole_image():
    depth, _ = tilted_plane()
    mask = np.zeros(depth.shape, bool)
    mask[31:70, 47:101] = True  # odd corners: the crop starts off the grid of every factor
    frame = Frame(0, "0", np.zeros(depth.shape + (3,), np.uint8), depth, K, mask)
    obs = preprocess(frame, mask, PreprocessConfig())
    rs, cs = obs.box
    assert obs.xyz.shape == depth.shape + (3,) and obs.valid.shape == depth.shape
    outside = np.ones(depth.shape, bool)
    outside[rs, cs] = False
    assert not obs.valid[outside].any() and not obs.depth[outside].any() and not obs.xyz[outside].any()
    assert obs.n_valid == obs.valid.sum() > 1000
    pts, nrm = obs.points()
    assert np.array_equal(pts, obs.xyz[obs.valid]) and np.array_equal(nrm, obs.normals[obs.valid])
    for factor in (2, 3, 4):
        xyz, _, _ = obs.grid(factor)
        whole = np.where(obs.valid[..., None], obs.xyz, 0)[::factor, ::factor]
        assert np.array_equal(xyz, whole)
    v, u = np.array([0, 40, 50, 119, 45]), np.array([0, 60, 90, 159, 49])  # two outside the crop
    ok, p, q = obs.at(v, u)
    assert np.array_equal(ok, obs.valid[v, u]) and ok[1] and ok[2] and not ok[0] and not ok[3]
    assert np.array_equal(p, obs.xyz[v[ok], u[ok]]) and np.array_equal(q, obs.normals[v[ok], u[ok]])
    empty = preprocess(frame, np.zeros_like(mask), PreprocessConfig())
    assert empty.n_valid == 0 and not empty.valid.any() and not empty.at(v, u)[0].any()


@pytest.mark.parametrize("erosion", [0, 2])
def test_a_frame_masked_again_is_as_if_preprocessed_anew(erosion: int):
    """`remasked` (the tracker's second mask of a frame, at its tracked pose): in the same crop the filtered depth,
    points and normals are the first mask's, reused; in another crop the frame is preprocessed anew."""
    depth, _ = tilted_plane()
    depth = depth + np.random.default_rng(0).normal(0.0, 0.001, depth.shape).astype(np.float32)
    depth[50:54, 60:66] = 0  # a hole the filter must keep out
    cfg = PreprocessConfig(mask_erosion=erosion)
    first = np.zeros(depth.shape, bool)
    first[30:70, 40:100] = True
    second = first.copy()
    second[40:55, 55:80] = False  # the same box, another mask
    frame = Frame(0, "0", np.zeros(depth.shape + (3,), np.uint8), depth, K, None)
    obs = preprocess(frame, first, cfg, mask_given=False)
    for mask, same_crop in ((second, True), (np.roll(first, 7, axis=1), False)):
        again, fresh = remasked(obs, mask, cfg), preprocess(frame, mask, cfg, mask_given=False)
        assert (again.box == obs.box) == same_crop and again.box == fresh.box and not again.mask_given
        for name in ("crop_depth", "crop_xyz", "crop_normals", "crop_valid", "crop_trusted"):
            assert np.array_equal(getattr(again, name), getattr(fresh, name)), name
        assert np.shares_memory(again.crop_xyz, obs.crop_xyz) == same_crop
    assert remasked(obs, second, cfg).n_valid < obs.n_valid
