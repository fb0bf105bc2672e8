"""Baseline trackers behind SurgTracker's API: KinectFusion (TSDF + frame-to-model ICP), frame-to-frame ICP, and
RANSAC on SIFT matches against the previous frame only.

    tracker = KinectFusionTracker()
    pose = tracker.register(frame, mask)          # first frame: fixes the object frame as SurgTracker does
    result = tracker.track(frame, mask=None)      # mask None: predicted from the model at the last pose

Every baseline uses the same object frame (origin at ``object_origin`` of the first masked cloud, axes of the first
camera), the same preprocessing, and reports a frame it cannot track as lost with no pose.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import replace

import cv2
import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial import cKDTree

from .config import TrackerConfig
from .features import FeatureExtractor, Features, match
from .geometry import backproject, inv_T, make_T, orthonormalize, transform, voxel_downsample
from .global_registration import icp, point_cloud
from .io import Frame
from .masking import predict_mask
from .preprocess import Observation, preprocess
from .ransac import plausible, ransac_pose
from .tracker import LOST, NO_POSE, RELOCALISED, TRACKED, TrackResult, object_origin, unseen


def surface_mask(obs: Observation, erosion: int) -> np.ndarray:
    """Every instrument pixel with filtered depth, the mask eroded by ``erosion`` pixels.

    Unlike ``Observation.valid`` this keeps pixels whose normal is unknown or grazing: ICP, TSDF fusion and RANSAC
    without normals need none, and a thin shaft a few pixels wide has few pixels with a trusted one."""
    m = obs.mask.astype(np.uint8)
    if erosion > 0:
        m = cv2.erode(m, np.ones((2 * erosion + 1,) * 2, np.uint8))
    return (m > 0) & (obs.depth > 0)


class BaselineTracker(ABC):
    """What the baselines share: the object frame, preprocessing, mask prediction and lost-frame bookkeeping.

    Subclasses implement ``_step(obs) -> (pose | None, confidence)`` and ``_update(obs, pose)``, which takes a
    tracked frame (the first one included) into the tracker's state. A frame whose mask was predicted is taken in
    only where its points lie within ``consistency_dist`` of the model: a predicted mask also covers background
    near the instrument, which would otherwise join the model and grow the next prediction.
    """

    def __init__(self, config: TrackerConfig | None = None, consistency_dist: float = 0.005):
        self.cfg = config or TrackerConfig()
        self.consistency_dist = consistency_dist
        self.pose: np.ndarray | None = None  # the last tracked pose
        self.lost = False
        self.model_points: np.ndarray | None = None  # what the tracker knows of the instrument, object frame

    def register(self, frame: Frame, mask: np.ndarray) -> np.ndarray:
        """Start tracking on the first frame and its instrument mask; returns the first pose."""
        obs = preprocess(frame, mask, self.cfg.preprocess)
        n = len(self._points(obs))
        if n < self.cfg.failure.min_pixels:
            raise ValueError(
                f"frame {frame.id}: only {n} instrument pixels with valid depth in the first mask "
                f"(need {self.cfg.failure.min_pixels})"
            )
        pts, _ = backproject(frame.depth, frame.K, mask)
        self.pose = make_T(np.eye(3), object_origin(pts))
        self._update(obs, self.pose)
        return self.pose

    def first_result(self, pose: np.ndarray) -> TrackResult:
        """The first frame's result, its ``pose`` from `register`: tracked."""
        return TrackResult(pose, TRACKED, 1.0)

    def track(self, frame: Frame, mask: np.ndarray | None = None) -> TrackResult:
        """One tracking step; a frame with too few instrument pixels or a failed alignment is lost (pose None)."""
        t0 = time.perf_counter()
        predicted = mask is None
        if mask is None:
            mask = self._predicted_mask(frame)
        obs = preprocess(frame, mask, self.cfg.preprocess)
        t1 = time.perf_counter()
        timings = {"preprocess": t1 - t0}
        enough = len(self._points(obs)) >= self.cfg.failure.min_pixels
        pose, confidence = self._step(obs) if enough else (None, 0.0)
        if pose is not None:
            self._update(self._model_consistent(obs, pose) if predicted else obs, pose)
        timings["track"] = time.perf_counter() - t1
        if pose is None:
            self.lost = True
            return TrackResult(None, LOST, confidence, timings,
                               reason=NO_POSE if enough else unseen(mask, self.cfg.failure.min_pixels))
        status = RELOCALISED if self.lost else TRACKED
        self.lost = False
        self.pose = pose
        return TrackResult(pose, status, confidence, timings)

    def mesh(self) -> trimesh.Trimesh | None:
        """The reconstructed instrument (object frame, metres), or None for a tracker that builds no surface."""
        return None

    def _predicted_mask(self, frame: Frame) -> np.ndarray:
        if self.model_points is None or self.pose is None:
            return np.zeros(frame.depth.shape, bool)
        pre = self.cfg.preprocess
        return predict_mask(self.model_points, self.pose, frame.K, frame.depth, pre.predicted_mask_margin,
                            pre.predicted_mask_tol)

    def _model_consistent(self, obs: Observation, pose: np.ndarray) -> Observation:
        """The observation with its mask cut to pixels whose point at ``pose`` lies near the model points."""
        if self.model_points is None:
            return obs
        rows, cols = np.nonzero(self._surface(obs))
        dist, _ = cKDTree(self.model_points).query(transform(inv_T(pose), obs.xyz[rows, cols]),
                                                   distance_upper_bound=self.consistency_dist)
        far = ~np.isfinite(dist)
        mask = obs.mask.copy()
        mask[rows[far], cols[far]] = False
        return replace(obs, mask=mask)

    def _surface(self, obs: Observation) -> np.ndarray:
        return surface_mask(obs, self.cfg.preprocess.mask_erosion)

    def _points(self, obs: Observation) -> np.ndarray:
        """Camera-frame points of the instrument's ``_surface`` pixels."""
        return obs.xyz[self._surface(obs)].astype(np.float64)

    @abstractmethod
    def _update(self, obs: Observation, pose: np.ndarray) -> None:
        """Take a tracked frame at its pose into the tracker's state."""

    @abstractmethod
    def _step(self, obs: Observation) -> tuple[np.ndarray | None, float]:
        """Pose of a frame (None when it cannot be aligned) and a confidence in [0, 1]."""


class KinectFusionTracker(BaselineTracker):
    """KinectFusion on the masked depth: a TSDF (Open3D VoxelBlockGrid) fused in the object frame and frame-to-model
    point-to-plane ICP against the fused surface as seen from the last pose (its camera-facing zero crossings).
    ICP fitness below ``min_fitness`` is lost, and a lost frame is not fused."""

    def __init__(self, config: TrackerConfig | None = None, voxel_size: float = 0.002, trunc_voxels: float = 4.0,
                 icp_dists: tuple[float, ...] = (0.02, 0.01, 0.005), min_fitness: float = 0.5,
                 max_points: int = 3000):
        super().__init__(config)
        self.voxel_size = voxel_size
        self.trunc_voxels = trunc_voxels
        self.icp_dists = icp_dists
        self.min_fitness = min_fitness
        self.max_points = max_points
        self.device = o3d.core.Device("CPU:0")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3d.core.float32, o3d.core.float32),
            attr_channels=((1,), (1,)), voxel_size=voxel_size, block_resolution=8, block_count=20000,
            device=self.device)

    def mesh(self) -> trimesh.Trimesh | None:
        """Marching cubes of the fused TSDF (object frame, metres); None before anything is fused."""
        if self.model_points is None:
            return None
        m = self.vbg.extract_triangle_mesh(weight_threshold=0.5).to_legacy()
        if len(m.triangles) == 0:
            return None
        return trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.triangles), process=False)

    def _step(self, obs: Observation) -> tuple[np.ndarray | None, float]:
        assert self.pose is not None
        target = self._model_view(self.pose)
        if target is None:
            return None, 0.0
        pts = self._points(obs)
        pts = pts[:: max(1, len(pts) // self.max_points)]
        # Source: the frame's points (camera); target: the model (object frame); so T = inv(pose).
        T, fitness = icp(pts, target[0], inv_T(self.pose), self.icp_dists, target[1])
        if fitness < self.min_fitness:
            return None, fitness
        return inv_T(T), fitness

    def _update(self, obs: Observation, pose: np.ndarray) -> None:
        """Fuse the frame's instrument depth into the TSDF at ``pose`` (the extrinsic maps object to camera)."""
        depth = np.ascontiguousarray(np.where(self._surface(obs), obs.depth, 0.0), np.float32)
        img = o3d.t.geometry.Image(o3d.core.Tensor(depth, device=self.device))
        K = o3d.core.Tensor(np.asarray(obs.K, np.float64))
        ext = o3d.core.Tensor(np.asarray(pose, np.float64))
        far = self.cfg.preprocess.max_depth
        blocks = self.vbg.compute_unique_block_coordinates(img, K, ext, 1.0, far, self.trunc_voxels)
        self.vbg.integrate(blocks, img, K, ext, 1.0, far, self.trunc_voxels)
        new = transform(inv_T(pose), self._points(obs))
        both = new if self.model_points is None else np.concatenate([self.model_points, new])
        self.model_points = voxel_downsample(both, self.voxel_size)

    def _model_view(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """The fused surface's zero crossings that face the camera at ``pose`` (object frame, with normals)."""
        try:
            pc = self.vbg.extract_point_cloud(weight_threshold=0.5)
        except RuntimeError:  # Open3D raises instead of returning an empty cloud
            return None
        if "normals" not in pc.point or len(pc.point.positions) < 10:
            return None
        p = pc.point.positions.numpy().astype(np.float64)
        n = pc.point.normals.numpy().astype(np.float64)
        cam = inv_T(pose)[:3, 3]
        facing = np.einsum("ij,ij->i", n, cam - p) > 0
        if facing.sum() < 10:
            return None
        return p[facing], n[facing]


class FrameToFrameICPTracker(BaselineTracker):
    """Point-to-plane ICP of each masked cloud onto the last tracked frame's, poses chained; fitness below
    ``min_fitness`` is lost (the next frame is aligned to the last tracked one again)."""

    def __init__(self, config: TrackerConfig | None = None, icp_dists: tuple[float, ...] = (0.02, 0.01, 0.005),
                 min_fitness: float = 0.5, max_points: int = 3000, normal_radius: float = 0.006):
        super().__init__(config)
        self.icp_dists = icp_dists
        self.min_fitness = min_fitness
        self.max_points = max_points
        self.normal_radius = normal_radius
        self._prev: tuple[np.ndarray, np.ndarray] | None = None  # last tracked frame's points and normals (camera)

    def _step(self, obs: Observation) -> tuple[np.ndarray | None, float]:
        assert self.pose is not None and self._prev is not None
        pts = self._points(obs)
        pts = pts[:: max(1, len(pts) // self.max_points)]
        T, fitness = icp(pts, self._prev[0], np.eye(4), self.icp_dists, self._prev[1])  # current -> previous
        if fitness < self.min_fitness:
            return None, fitness
        return orthonormalize(inv_T(T) @ self.pose), fitness

    def _update(self, obs: Observation, pose: np.ndarray) -> None:
        """Keep the frame's points with normals (k nearest neighbours, facing the camera) as the next target."""
        pts = self._points(obs)
        pc = point_cloud(pts)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=self.normal_radius, max_nn=30))
        pc.orient_normals_towards_camera_location(np.zeros(3))
        self._prev = pts, np.asarray(pc.normals)
        self.model_points = transform(inv_T(pose), pts)


class RansacOnlyTracker(BaselineTracker):
    """Features (SIFT by default) matched with the last tracked frame only, RANSAC over 3-point hypotheses and
    Kabsch on the inliers (``ransac.ransac_pose``); no memory pool, no posture graph, no SDF. Too few inliers or an
    implausible jump is lost.

    Keypoints are lifted to 3D on every ``_surface`` pixel and RANSAC gates on distance only: on a thin shaft the
    pixels with a trusted normal carry a handful of keypoints, too few for a 3-point RANSAC."""

    def __init__(self, config: TrackerConfig | None = None):
        super().__init__(config)
        self.extractor = FeatureExtractor(self.cfg.ransac.features, self.cfg.ransac.max_keypoints)
        self.rng = np.random.default_rng(self.cfg.seed)
        self._prev: Features | None = None  # the last tracked frame's features
        self._current: Features | None = None  # the features of the frame being tracked

    def _step(self, obs: Observation) -> tuple[np.ndarray | None, float]:
        assert self.pose is not None and self._prev is not None
        feats = self._current = self._features(obs)
        ia, ib = match(self._prev, feats, self.extractor.norm, self.cfg.ransac.ratio_test)
        if len(ia) < self.cfg.ransac.min_inliers:
            return None, 0.0
        src, dst = self._prev.subset(ia), feats.subset(ib)
        res = ransac_pose(src.xyz, dst.xyz, self.cfg.ransac, self.rng)
        if res.T is None or not plausible(res.T, self.cfg.ransac):
            return None, 0.0
        return orthonormalize(res.T @ self.pose), res.n_inliers / len(ia)

    def _features(self, obs: Observation) -> Features:
        """Keypoints in the instrument mask, lifted on every ``_surface`` pixel."""
        return self.extractor(replace(obs, crop_valid=self._surface(obs)[obs.box]))  # no depth beyond the box

    def _update(self, obs: Observation, pose: np.ndarray) -> None:
        """Keep the frame's features on its (model-consistent) instrument pixels as the next reference."""
        feats = self._current if self._current is not None else self._features(obs)
        surface = self._surface(obs)
        u = np.clip(np.round(feats.uv[:, 0]).astype(int), 0, surface.shape[1] - 1)
        v = np.clip(np.round(feats.uv[:, 1]).astype(int), 0, surface.shape[0] - 1)
        self._prev = feats.subset(np.nonzero(surface[v, u])[0])
        self._current = None
        self.model_points = transform(inv_T(pose), obs.xyz[surface].astype(np.float64))
