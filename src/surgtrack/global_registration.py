"""Geometric registration of a frame's instrument points against the model: global (FPFH + RANSAC, then ICP) and
coarse-to-fine ICP from a pose guess.

Used where texture is too weak for feature re-localisation, and to find the first pose against a registered model.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .geometry import inv_T, make_T, orthonormalize, transform

_REG = o3d.pipelines.registration
FPFH_VOXEL = 0.004  # m: the clouds of global registration are downsampled to this before their FPFH features


@contextmanager
def one_thread() -> Iterator[None]:
    """Open3D on one thread within (or in a function it decorates): over several, its RANSAC (and its ICP's sums)
    depend on which thread finishes first, so the same call with the same seed gives another pose now and then, and
    tracking runs do not repeat."""
    before = o3d.utility.get_max_threads()
    o3d.utility.set_max_threads(1)
    try:
        yield
    finally:
        o3d.utility.set_max_threads(before)


def point_cloud(points: np.ndarray, normals: np.ndarray | None = None, voxel: float = 0.0) -> o3d.geometry.PointCloud:
    """Open3D cloud of (N, 3) points, with normals when given, voxel-downsampled when ``voxel`` > 0."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    return pc.voxel_down_sample(voxel) if voxel > 0 else pc


@one_thread()
def icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, max_dists: Sequence[float],
        target_normals: np.ndarray | None = None, iterations: int = 20) -> tuple[np.ndarray, float]:
    """Coarse-to-fine ICP (Open3D) of ``source`` points onto ``target`` points from ``init``, one pass per
    correspondence gate in ``max_dists``: (T with target ~ T @ source, fitness at the last gate). Point-to-plane
    (Tukey-robust) when ``target_normals`` are given, point-to-point otherwise.

    Both clouds are expressed about the target's centroid while aligning: Open3D linearises rotations about the
    origin, and about a far-away camera centre rotation and translation of a thin object are nearly degenerate."""
    c = make_T(np.eye(3), -np.mean(target, axis=0))
    src = point_cloud(transform(c, source))
    tgt = point_cloud(transform(c, target), target_normals)
    T = c @ np.asarray(init, np.float64) @ inv_T(c)
    fitness = 0.0
    for d in max_dists:
        est = (_REG.TransformationEstimationPointToPoint() if target_normals is None
               else _REG.TransformationEstimationPointToPlane(_REG.TukeyLoss(k=d / 2)))
        res = _REG.registration_icp(src, tgt, d, T, est, _REG.ICPConvergenceCriteria(max_iteration=iterations))
        T, fitness = np.asarray(res.transformation), float(res.fitness)
    return orthonormalize(inv_T(c) @ T @ c), fitness


@dataclass(frozen=True)
class FpfhCloud:
    """Points voxel-downsampled, with normals and FPFH features: one side of `global_register`. The model's side is
    the same on every re-localisation until the model changes, so a caller may compute it once."""

    source: np.ndarray  # the points as given, before the downsampling
    voxel: float
    cloud: o3d.geometry.PointCloud
    fpfh: _REG.Feature

    @classmethod
    @one_thread()
    def of(cls, points: np.ndarray, voxel: float = FPFH_VOXEL) -> FpfhCloud:
        """``points`` downsampled to ``voxel`` (m), normals within 2.5 voxels, FPFH within 5."""
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
        pcd = point_cloud(points, voxel=voxel)
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
        fpfh = _REG.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
        return cls(points, voxel, pcd, fpfh)


def overlap(model_tree: cKDTree, pose: np.ndarray, points_cam: np.ndarray, dist: float) -> float:
    """Fraction of camera-frame points within ``dist`` of the model placed at ``pose``."""
    d, _ = model_tree.query(transform(np.linalg.inv(pose), points_cam), distance_upper_bound=dist)
    return float(np.mean(np.isfinite(d)))


@one_thread()
def global_register(points_cam: np.ndarray, model_obj: np.ndarray | FpfhCloud, voxel: float = FPFH_VOXEL,
                    seeds: Sequence[int] = (0,), iterations: int = 50_000) -> list[tuple[np.ndarray, float]]:
    """Poses (object-to-camera) that lay the model on the frame's points, one per RANSAC seed, each with the fraction
    of those points it explains (within 2 voxels); empty when there are too few points. The clouds, their FPFH
    features and the features' matches are computed once for all seeds; the model's may come computed already
    (`FpfhCloud`)."""
    given = model_obj if isinstance(model_obj, FpfhCloud) else None
    model_pts = given.source if given is not None else model_obj
    if len(points_cam) < 30 or len(model_pts) < 30:
        return []
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    model = given if given is not None and given.voxel == voxel else FpfhCloud.of(model_pts, voxel)
    frame = FpfhCloud.of(points_cam, voxel)
    src, src_f, dst, dst_f = model.cloud, model.fpfh, frame.cloud, frame.fpfh
    if len(src.points) < 10 or len(dst.points) < 10:
        return []
    gate = 2.0 * voxel
    tree, dst_pts = cKDTree(np.asarray(src.points)), np.asarray(dst.points)
    # The mutual FPFH matches, found once for all seeds: Open3D's feature-matching RANSAC finds them again per call
    # (most of a call's time on a large cloud), and from the same matches gives the same pose.
    matches = _REG.correspondences_from_features(src_f, dst_f, True)
    found = []
    for seed in seeds:
        o3d.utility.random.seed(seed)
        coarse = _REG.registration_ransac_based_on_correspondence(
            src, dst, matches, gate, _REG.TransformationEstimationPointToPoint(False), 3,
            [_REG.CorrespondenceCheckerBasedOnEdgeLength(0.9), _REG.CorrespondenceCheckerBasedOnDistance(gate)],
            _REG.RANSACConvergenceCriteria(iterations, 0.999))
        fine = _REG.registration_icp(src, dst, gate, coarse.transformation, _REG.TransformationEstimationPointToPlane())
        # Point-to-plane ICP can slide off a round shaft it cannot pin: keep whichever pose explains more.
        scored = [(overlap(tree, T, dst_pts, gate), T) for T in (np.array(fine.transformation),
                                                                 np.array(coarse.transformation))]
        explained, pose = max(scored, key=lambda sc: sc[0])
        found.append((pose, explained))
    return found


def icp_from(points_cam: np.ndarray, model_obj: np.ndarray, init: np.ndarray,
             gates: Sequence[float] = (0.05, 0.02, 0.008), voxel: float = 0.003) -> np.ndarray:
    """Pose (object-to-camera) that lays the model on the frame's points, by point-to-point ICP from ``init`` with
    correspondence gates shrinking through ``gates`` (m): an instrument that moved a few centimetres while it was
    out of sight is pulled in before the narrow gate pins it. ``init`` is returned when there are too few points."""
    if len(points_cam) < 30 or len(model_obj) < 30:
        return init
    # The frame's points are matched to the model, not the other way: the model has sides the frame does not show.
    seen = np.asarray(point_cloud(points_cam, voxel=voxel).points)
    model = np.asarray(point_cloud(model_obj, voxel=voxel).points)
    cam_to_obj, _ = icp(seen, model, inv_T(init), gates, iterations=30)
    return inv_T(cam_to_obj)
