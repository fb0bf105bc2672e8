"""Coarse pose by 3-point RANSAC and Kabsch (paper eq. 5) and the physical-plausibility gate."""

from __future__ import annotations

import numpy as np

from surgtrack.config import RansacConfig
from surgtrack.geometry import make_T, rotation_angle_deg, so3_exp, transform
from surgtrack.ransac import plausible, ransac_pose

T_TRUE = make_T(so3_exp(np.array([0.3, -0.2, 0.25])), np.array([0.03, -0.02, 0.05]))


def matches(rng: np.random.Generator, n: int, outlier_frac: float, noise: float = 0.001):
    """Points on an instrument-sized region 0.4 m away, their images under T_TRUE with noise, a share replaced by
    random wrong matches. Returns src, dst, unit normals for both and the true-inlier mask."""
    src = rng.uniform([-0.05, -0.04, 0.37], [0.05, 0.04, 0.43], (n, 3))
    src_n = rng.normal(size=(n, 3))
    src_n /= np.linalg.norm(src_n, axis=1, keepdims=True)
    dst = transform(T_TRUE, src) + rng.normal(0.0, noise, (n, 3))
    dst_n = src_n @ T_TRUE[:3, :3].T
    wrong = rng.random(n) < outlier_frac
    dst[wrong] = rng.uniform([-0.05, -0.04, 0.37], [0.05, 0.04, 0.43], (wrong.sum(), 3))
    dst_n[wrong] = rng.normal(size=(wrong.sum(), 3))
    dst_n /= np.linalg.norm(dst_n, axis=1, keepdims=True)
    return src, dst, src_n, dst_n, ~wrong


def errors(T: np.ndarray) -> tuple[float, float]:
    """Rotation error (degrees) and translation error (m) at the object, i.e. of the region's centre."""
    c = np.array([[0.0, 0.0, 0.4]])
    rot = rotation_angle_deg(T[:3, :3] @ T_TRUE[:3, :3].T)
    return rot, float(np.linalg.norm(transform(T, c) - transform(T_TRUE, c)))


def test_recovers_transform_with_60_percent_outliers():
    rng = np.random.default_rng(0)
    src, dst, _, _, good = matches(rng, 500, 0.6)
    res = ransac_pose(src, dst, RansacConfig(), rng)
    assert res.ok
    rot, trans = errors(res.T)
    assert rot < 0.5
    assert trans < 0.002
    assert res.n_inliers == res.inliers.sum()
    assert (res.inliers & good).sum() >= 0.97 * good.sum()
    assert (res.inliers & ~good).sum() <= 0.03 * (~good).sum()
    assert 0.0005 < res.rmse < 0.003


def test_recovers_transform_with_normals():
    rng = np.random.default_rng(1)
    src, dst, src_n, dst_n, good = matches(rng, 500, 0.6)
    res = ransac_pose(src, dst, RansacConfig(), rng, src_n, dst_n)
    rot, trans = errors(res.T)
    assert rot < 0.5 and trans < 0.002
    assert (res.inliers & ~good).sum() == 0  # a wrong match rarely agrees in position and normal


def test_normal_test_rejects_wrong_normals():
    rng = np.random.default_rng(2)
    src, dst, src_n, dst_n, good = matches(rng, 200, 0.0)
    flipped = np.arange(200) % 4 == 0  # positions agree, normals 90 degrees off
    perp = np.cross(dst_n[flipped], rng.normal(size=(flipped.sum(), 3)))
    dst_n[flipped] = perp / np.linalg.norm(perp, axis=1, keepdims=True)
    cfg = RansacConfig()
    with_n = ransac_pose(src, dst, cfg, np.random.default_rng(3), src_n, dst_n)
    without_n = ransac_pose(src, dst, cfg, np.random.default_rng(3))
    assert without_n.inliers[flipped].all()
    assert not with_n.inliers[flipped].any()
    assert with_n.inliers[~flipped].all()
    assert errors(with_n.T)[0] < 0.5


def test_too_few_points_fail_cleanly():
    rng = np.random.default_rng(4)
    cfg = RansacConfig()
    for n in (0, 1, 2):
        res = ransac_pose(np.zeros((n, 3)), np.zeros((n, 3)), cfg, rng)
        assert res.T is None and not res.ok
        assert res.n_inliers == 0 and res.inliers.shape == (n,)
    # Four true matches cannot reach min_inliers = 5.
    src, dst, _, _, _ = matches(rng, 4, 0.0)
    res = ransac_pose(src, dst, cfg, rng)
    assert res.T is None and res.n_inliers <= 4
    assert res.inliers.shape == (4,)


def test_only_outliers_fail_cleanly():
    rng = np.random.default_rng(5)
    src = rng.uniform(-0.2, 0.2, (30, 3)) + [0.0, 0.0, 0.5]
    dst = rng.uniform(-0.2, 0.2, (30, 3)) + [0.0, 0.0, 0.5]
    res = ransac_pose(src, dst, RansacConfig(), rng)
    assert res.T is None
    assert res.rmse == float("inf")


def test_degenerate_samples_are_rejected():
    rng = np.random.default_rng(6)
    t = rng.uniform(0, 0.1, 50)
    src = np.stack([t, 2 * t, np.full(50, 0.4)], axis=1)  # collinear: rotation about the line is unobservable
    res = ransac_pose(src, transform(T_TRUE, src), RansacConfig(), rng)
    assert res.T is None
    same = np.tile([0.0, 0.0, 0.4], (30, 1))  # coincident
    assert ransac_pose(same, same, RansacConfig(), rng).T is None


def test_large_match_sets_are_scored_in_blocks():
    rng = np.random.default_rng(7)
    src, dst, _, _, _ = matches(rng, 3000, 0.5)
    res = ransac_pose(src, dst, RansacConfig(hypotheses=1000), rng)
    rot, trans = errors(res.T)
    assert rot < 0.5 and trans < 0.002


def test_same_seed_same_result():
    src, dst, _, _, _ = matches(np.random.default_rng(8), 300, 0.5)
    a = ransac_pose(src, dst, RansacConfig(), np.random.default_rng(9))
    b = ransac_pose(src, dst, RansacConfig(), np.random.default_rng(9))
    assert np.array_equal(a.T, b.T) and np.array_equal(a.inliers, b.inliers)


def test_few_matches_are_searched_exhaustively():
    """23 matches, 3 of them right: every one of the 1771 triples is tried, so the right one is found whatever the
    seed (2000 random draws miss it about a third of the time)."""
    rng = np.random.default_rng(10)
    src = rng.uniform([-0.05, -0.04, 0.37], [0.05, 0.04, 0.43], (23, 3))
    dst = rng.uniform(-0.5, 0.5, (23, 3)) + [0.0, 0.0, 1.0]  # wrong matches, far apart: no triple of them agrees
    dst[:3] = transform(T_TRUE, src[:3])
    cfg = RansacConfig(min_inliers=3)
    for seed in range(12):
        res = ransac_pose(src, dst, cfg, np.random.default_rng(seed))
        assert res.ok and res.inliers[:3].all() and res.n_inliers == 3
        rot, trans = errors(res.T)
        assert rot < 1e-6 and trans < 1e-9


def test_plausible_rejects_jumps():
    cfg = RansacConfig()
    assert plausible(np.eye(4), cfg)
    assert plausible(make_T(so3_exp(np.radians(10.0) * np.array([0.0, 0.0, 1.0])), np.array([0.03, 0.0, 0.02])), cfg)
    assert not plausible(make_T(np.eye(3), np.array([0.3, 0.0, 0.0])), cfg)
    assert not plausible(make_T(so3_exp(np.radians(90.0) * np.array([1.0, 0.0, 0.0])), np.zeros(3)), cfg)
    bad = np.eye(4)
    bad[0, 3] = np.nan
    assert not plausible(bad, cfg)
