"""Synthetic sequence generator: ground truth consistent with the images, sensor bounds, determinism, suites."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from surgtrack.geometry import inv_T, transform
from surgtrack.io import FolderSequence, open_sequence, read_mask
from surgtrack.synth import SynthSpec, is_rendered, render_sequence, render_suite, suite_specs
from surgtrack.synth import suites as suites_mod
from surgtrack.synth.sensor import depth_error_bound

SMALL = dict(width=320, height=240)


def model_zbuffer(mesh: trimesh.Trimesh, T: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """Z-depth of the posed model at every pixel centre (0 = miss), ray-cast with embree in the object frame."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    Ti = inv_T(T)
    origins = np.repeat(Ti[:3, 3][None, :], len(d_cam), 0)
    dirs = d_cam @ Ti[:3, :3].T
    locs, idx, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=False)
    z = np.zeros(len(d_cam))
    z[idx] = transform(T, locs)[:, 2]
    return z.reshape(h, w)


@pytest.fixture(scope="module")
def clean_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    spec = SynthSpec(instrument="forceps", frames=12, n_occluders=0, seed=3, **SMALL)
    return render_sequence(spec, tmp_path_factory.mktemp("synth") / "clean")


def test_gt_pose_reprojects_model_onto_mask(clean_seq: Path) -> None:
    seq = FolderSequence(clean_seq)
    poses = seq.gt_poses()
    mesh = seq.gt_model()
    ious = []
    for i in (0, 5, 11):
        f = seq[i]
        sil = model_zbuffer(mesh, poses[f.id], seq.K, f.depth.shape[1], f.depth.shape[0]) > 0
        assert f.mask.sum() > 200
        ious.append((sil & f.mask).sum() / (sil | f.mask).sum())
    assert min(ious) > 0.95, ious


def test_depth_matches_model_within_noise_bounds(clean_seq: Path) -> None:
    seq = FolderSequence(clean_seq)
    poses, mesh = seq.gt_poses(), seq.gt_model()
    valid_frac, noisy = [], 0
    for i in (0, 6, 11):
        f = seq[i]
        z = model_zbuffer(mesh, poses[f.id], seq.K, f.depth.shape[1], f.depth.shape[0])
        box = np.ones((5, 5), np.uint8)
        zf = z.astype(np.float32)
        smooth = cv2.dilate(zf, box) - cv2.erode(np.where(z > 0, zf, 1e3).astype(np.float32), box) < 0.01
        inner = cv2.erode(f.mask.astype(np.uint8), box).astype(bool) & (z > 0) & smooth  # no depth edge nearby
        meas = f.depth[inner]
        ok = meas > 0
        valid_frac.append(ok.mean())
        err = np.abs(meas[ok] - z[inner][ok])
        assert np.all(err <= depth_error_bound(z[inner][ok]) + 1e-4), err.max()
        noisy += int((err > 0.0006).sum())
    assert noisy > 0  # the sensor model does perturb the depth
    assert np.mean(valid_frac) > 0.35  # ... but leaves enough of a thin shaft to track


def test_visible_points_lie_on_model(clean_seq: Path) -> None:
    seq = FolderSequence(clean_seq)
    pts, mesh = seq.gt_visible_points(), seq.gt_model()
    surface, _ = trimesh.sample.sample_surface_even(mesh, 200_000, seed=0)
    d, _ = cKDTree(surface).query(pts)
    assert len(pts) > 100 and np.percentile(d, 95) < 0.0015
    spacing, _ = cKDTree(pts).query(pts, k=2)
    assert 0.0008 < np.median(spacing[:, 1]) < 0.0025
    # the model is bigger than what the camera saw (the handle is out of view)
    assert np.ptp(pts @ np.array([0, 0, 1.0])) < np.ptp(mesh.vertices[:, 2])


def test_same_seed_gives_identical_files(tmp_path: Path) -> None:
    spec = SynthSpec(instrument="ultrasound_probe", frames=4, width=160, height=120, n_occluders=1, seed=5,
                     full_occlusions=((2, 1),))
    a, b = render_sequence(spec, tmp_path / "a"), render_sequence(spec, tmp_path / "b")
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) >= 4 * 4 + 5
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    c = render_sequence(replace(spec, seed=6), tmp_path / "c")
    assert (a / "rgb" / "000000.png").read_bytes() != (c / "rgb" / "000000.png").read_bytes()


def test_occluders_reduce_the_mask(tmp_path: Path) -> None:
    base = SynthSpec(instrument="thoracoscope", frames=10, n_occluders=0, seed=11, **SMALL)
    free = render_sequence(base, tmp_path / "free")
    occ = render_sequence(replace(base, n_occluders=3), tmp_path / "occ")
    s_free, s_occ = FolderSequence(free), FolderSequence(occ)
    total_free = total_occ = 0
    for i in range(len(s_free)):
        m_free, m_occ = s_free[i].mask, s_occ[i].mask
        assert not (m_occ & ~m_free).any()  # occluders only hide; the instrument pose is the same
        total_free += m_free.sum()
        total_occ += m_occ.sum()
    assert total_occ < 0.95 * total_free
    for k, T in s_free.gt_poses().items():
        np.testing.assert_array_equal(T, s_occ.gt_poses()[k])


def test_full_occlusion_gives_empty_masks(tmp_path: Path) -> None:
    spec = SynthSpec(instrument="forceps", frames=24, n_occluders=1, seed=2, full_occlusions=((12, 5),), **SMALL)
    seq = render_sequence(spec, tmp_path / "full")
    masks = [read_mask(seq / "masks" / f"{i:06d}.png") for i in range(spec.frames)]
    assert all(not masks[i].any() for i in range(12, 17))
    assert masks[0].any() and masks[-1].any()


def test_sequence_opens_with_io(synth_seq: Path) -> None:
    seq = open_sequence(synth_seq)
    assert isinstance(seq, FolderSequence) and len(seq) == 30
    f0 = seq[0]
    assert f0.rgb.shape == (240, 320, 3) and f0.depth.shape == (240, 320) and f0.mask is not None and f0.mask.any()
    assert len(seq.gt_poses()) == 30 and seq.gt_model() is not None and len(seq.gt_visible_points()) > 100
    spec = SynthSpec(instrument="rigid_endoscope", frames=30, width=320, height=240, n_occluders=1, seed=7)
    np.testing.assert_allclose(seq.K, spec.K)
    assert is_rendered(spec, synth_seq) and not is_rendered(replace(spec, seed=8), synth_seq)
    assert (synth_seq / "preview.png").is_file()


def test_suites_list_procedural_sequences_and_skip_rendered(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("SURGTRACK_MESHES", str(tmp_path / "nowhere"))
    with pytest.warns(UserWarning, match="real meshes not found"):
        specs = suite_specs("instrument3d", short=True)
    assert len(specs) >= 10 and len({n for n, _ in specs}) == len(specs)
    assert all(s.frames == 40 and (s.width, s.height) == (320, 240) for _, s in specs)
    kinds = {s.instrument for _, s in specs}
    assert {"bronchoscope", "rigid_endoscope", "thoracoscope", "ultrasound_probe", "forceps"} <= kinds
    assert any(s.full_occlusions for _, s in specs) and any(s.n_occluders >= 2 for _, s in specs)
    with pytest.raises(FileNotFoundError):
        suite_specs("ho3d")

    tiny = SynthSpec(instrument="bronchoscope", frames=3, width=96, height=72, seed=1)
    monkeypatch.setattr(suites_mod, "suite_specs", lambda name, short=False, frames=None: [("b1", tiny)])
    (path,) = render_suite("instrument3d", tmp_path / "suite")
    stamp = (path / "rgb" / "000000.png").stat().st_mtime_ns
    assert render_suite("instrument3d", tmp_path / "suite") == [path]
    assert (path / "rgb" / "000000.png").stat().st_mtime_ns == stamp


def test_real_meshes_in_suites_when_available(shared_data: Path) -> None:
    names = {n for n, _ in suite_specs("instrument3d")}
    assert {"forceps_dvrk", "endoscope_dvrk"} <= names and len(names) == 13
    ho3d = suite_specs("ho3d", short=True)
    assert {s.instrument for _, s in ho3d} == {"ycb_power_drill", "ycb_mustard_bottle"}


def test_cli_synth(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from surgtrack.cli import app

    out = tmp_path / "cli_seq"
    res = CliRunner().invoke(app, ["synth", str(out), "--instrument", "forceps", "--frames", "3", "--size", "96x72",
                                   "--seed", "4", "--occluders", "0"])
    assert res.exit_code == 0, res.output
    assert len(list((out / "rgb").glob("*.png"))) == 3 and (out / "gt" / "model.ply").is_file()
    bad = CliRunner().invoke(app, ["synth", str(tmp_path / "x"), "--instrument", "no_such_tool"])
    assert bad.exit_code == 2
    bad = CliRunner().invoke(app, ["synth", str(tmp_path / "x"), "--frames", "0"])
    assert bad.exit_code == 2 and "0 frames" in bad.output


def test_cli_synth_cuts_a_suite_to_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from typer.testing import CliRunner

    from surgtrack.cli import app

    monkeypatch.setenv("SURGTRACK_MESHES", str(tmp_path / "nowhere"))  # the procedural sequences only
    out = tmp_path / "suite"
    with pytest.warns(UserWarning, match="real meshes not found"):
        res = CliRunner().invoke(app, ["synth", str(out), "--suite", "instrument3d", "--short", "--frames", "8"])
    assert res.exit_code == 0, res.output
    with pytest.warns(UserWarning, match="real meshes not found"):
        specs = dict(suite_specs("instrument3d", short=True, frames=8))
    assert sorted(p.name for p in out.iterdir()) == sorted(specs)
    for name, spec in specs.items():
        assert spec.frames == 8 and is_rendered(spec, out / name)
        assert len(list((out / name / "rgb").glob("*.png"))) == 8
    bad = CliRunner().invoke(app, ["synth", str(tmp_path / "x"), "--suite", "instrument3d", "--frames", "0"])
    assert bad.exit_code == 2 and "0 frames" in bad.output
    assert not (tmp_path / "x").exists()
    bad = CliRunner().invoke(app, ["synth", str(tmp_path / "x"), "--suite", "instrument3d", "--seed", "3",
                                   "--size", "320x240"])
    assert bad.exit_code == 2 and "--size, --seed: for one sequence" in bad.output
    assert not (tmp_path / "x").exists()
    # Cut to 3 frames, endoscope_2's hand covers the instrument from the first frame: no first mask to track from.
    with pytest.warns(UserWarning, match="real meshes not found"):
        bad = CliRunner().invoke(app, ["synth", str(out), "--suite", "instrument3d", "--short", "--frames", "3"])
    assert bad.exit_code == 2 and "not in view in the first frame" in bad.output
