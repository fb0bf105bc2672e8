"""Geometric registration of a frame's instrument points against the model: global (FPFH + RANSAC, then ICP) and
coarse-to-fine ICP from a pose guess.

Used where texture is too weak for feature re-localisation, and to find the first pose against a registered model.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from .geometry import transform


def _pcd(points: np.ndarray, voxel: float) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64))).voxel_down_sample(voxel)


def _cloud(points: np.ndarray, voxel: float) -> tuple[o3d.geometry.PointCloud, o3d.pipelines.registration.Feature]:
    pcd = _pcd(points, voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100))
    return pcd, fpfh


def overlap(model_tree: cKDTree, pose: np.ndarray, points_cam: np.ndarray, dist: float) -> float:
    """Fraction of camera-frame points within ``dist`` of the model placed at ``pose``."""
    d, _ = model_tree.query(transform(np.linalg.inv(pose), points_cam), distance_upper_bound=dist)
    return float(np.mean(np.isfinite(d)))


def global_register(points_cam: np.ndarray, model_obj: np.ndarray, voxel: float = 0.004, seeds: Sequence[int] = (0,),
                    iterations: int = 50_000) -> list[tuple[np.ndarray, float]]:
    """Poses (object-to-camera) that lay the model on the frame's points, one per RANSAC seed, each with the fraction
    of those points it explains (within 2 voxels); empty when there are too few points. The clouds and their FPFH
    features are computed once for all seeds."""
    if len(points_cam) < 30 or len(model_obj) < 30:
        return []
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    src, src_f = _cloud(model_obj, voxel)
    dst, dst_f = _cloud(points_cam, voxel)
    if len(src.points) < 10 or len(dst.points) < 10:
        return []
    gate = 2.0 * voxel
    tree, dst_pts = cKDTree(np.asarray(src.points)), np.asarray(dst.points)
    found = []
    for seed in seeds:
        o3d.utility.random.seed(seed)
        coarse = reg.registration_ransac_based_on_feature_matching(
            src, dst, src_f, dst_f, True, gate, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(gate)],
            reg.RANSACConvergenceCriteria(iterations, 0.999))
        fine = reg.registration_icp(src, dst, gate, coarse.transformation, reg.TransformationEstimationPointToPlane())
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
    reg = o3d.pipelines.registration
    # The frame's points are matched to the model, not the other way: the model has sides the frame does not show.
    seen, model = _pcd(points_cam, voxel), _pcd(model_obj, voxel)
    cam_to_obj = np.linalg.inv(np.asarray(init, np.float64))
    for gate in gates:
        cam_to_obj = np.array(reg.registration_icp(seen, model, gate, cam_to_obj,
                                                   reg.TransformationEstimationPointToPoint(),
                                                   reg.ICPConvergenceCriteria(max_iteration=30)).transformation)
    return np.linalg.inv(cam_to_obj)
