"""Geometry helpers the tracker's model relies on."""

from __future__ import annotations

import numpy as np
import pytest

from surgtrack.geometry import (
    make_T,
    rotation_angle_deg,
    rotation_gaps_deg,
    so3_exp,
    span,
    transform,
    voxel_downsample,
)


def first_per_voxel(p: np.ndarray, voxel: float) -> np.ndarray:
    """Reference: walk the points in order, keep each one whose voxel has not been seen."""
    seen, keep = set(), []
    for i, key in enumerate(map(tuple, np.floor(p / voxel).astype(np.int64))):
        if key not in seen:
            seen.add(key)
            keep.append(i)
    return p[keep]


@pytest.mark.parametrize("spread", [0.03, 1e15])  # an instrument's cloud; a range too wide for one int64 key
def test_voxel_downsample_keeps_the_first_point_of_each_voxel_in_order(spread: float) -> None:
    rng = np.random.default_rng(3)
    p = rng.normal(size=(4000, 3)) * 0.03
    p[::7] = p[::3][: len(p[::7])]  # repeated points fall into occupied voxels
    p[0] = [-spread, 0.0, spread]
    out = voxel_downsample(p, 0.002)
    np.testing.assert_array_equal(out, first_per_voxel(p, 0.002))
    assert len(out) < len(p)


def test_rotation_gaps_to_many_poses_equal_the_angle_of_each_relative_rotation() -> None:
    rng = np.random.default_rng(4)
    T = make_T(so3_exp(rng.normal(size=3)), rng.normal(size=3))
    poses = np.stack([make_T(so3_exp(rng.normal(size=3) * s), rng.normal(size=3)) for s in (0.0, 0.01, 0.5, 3.0)])
    poses[0][:3, :3] = T[:3, :3]  # no gap at all
    want = [rotation_angle_deg(T[:3, :3] @ P[:3, :3].T) for P in poses]
    np.testing.assert_allclose(rotation_gaps_deg(T, poses), want, atol=1e-5)
    assert rotation_gaps_deg(T, poses)[0] < 1e-5


def test_span_is_a_shafts_length_whatever_a_few_stray_points_say() -> None:
    shaft = np.stack([np.linspace(-0.1, 0.1, 1000), np.zeros(1000), np.full(1000, 0.3)], axis=1)
    stray = np.array([[1.0, 1.0, 2.0]] * 10)  # 1 % of the points, a metre off
    T = make_T(so3_exp(np.array([0.3, -0.2, 1.0])), np.array([0.1, 0.0, 0.2]))
    for points in (shaft, np.vstack([shaft, stray]), transform(T, shaft)):
        assert span(points) == pytest.approx(0.2, abs=0.01)
    assert span(np.empty((0, 3))) == 0.0
