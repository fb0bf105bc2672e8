"""Posture memory pool P = {(xi_i, M_i)} (paper eq. 6): keyframes with pose, geometry and features.

Add rule (BundleSDF's): a frame becomes a keyframe when its rotation differs by at least ``keyframe_rot_deg`` from
every keyframe. Unlike BundleSDF the pool is capped; when full, the most redundant keyframe (the one whose nearest
neighbour in viewing direction is closest) is dropped, never the first, so the pool keeps its view coverage.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .config import PoolConfig
from .features import Features
from .geometry import rotation_gaps_deg
from .posture_graph import GridPoints, MaskView
from .preprocess import MaskEdge


@dataclass(eq=False)
class Keyframe:
    """One memory: pose xi_i (object-to-camera) and memory M_i (features, geometry grid, masked depth)."""

    frame_id: str
    pose: np.ndarray
    features: Features  # camera frame of this keyframe
    xyz: np.ndarray  # (h, w, 3) downscaled camera-frame grid for projective association
    normals: np.ndarray
    K_grid: np.ndarray
    depth: np.ndarray  # (H, W) metres, full resolution, for the SDF fit
    mask: np.ndarray  # (H, W) bool
    K: np.ndarray
    tracked_pose: np.ndarray | None = None  # the pose tracking gave it (pose may be refined with the SDF since)
    image: np.ndarray | None = None  # (H, W) uint8 intensity, for the appearance check of re-localisation

    def __post_init__(self) -> None:
        if self.tracked_pose is None:
            self.tracked_pose = self.pose.copy()

    @cached_property
    def grid_points(self) -> GridPoints:
        """The grid's valid points for the posture graph, found once."""
        return GridPoints.of(self.xyz, self.normals)

    @cached_property
    def view(self) -> MaskView:
        """What it saw past (`posture_graph.MaskView`: its mask, the mask's edge, its depth), built once: L_CV reads
        the first keyframe's on every frame."""
        return MaskView.of(MaskEdge.of(self.mask), self.depth, self.K)

    @cached_property
    def area(self) -> int:
        """Pixels in its instrument mask."""
        return int(np.count_nonzero(self.mask))

    @property
    def view_dir(self) -> np.ndarray:
        """The camera's optical axis in the object frame."""
        return self.pose[2, :3]


class MemoryPool:
    """The capped set of keyframes."""

    def __init__(self, cfg: PoolConfig):
        self.cfg = cfg
        self.keyframes: list[Keyframe] = []

    def __len__(self) -> int:
        return len(self.keyframes)

    def should_add(self, pose: np.ndarray, predicted_area: int | None = None) -> bool:
        """Add rule: rotation differs by >= keyframe_rot_deg from every keyframe; for a frame whose mask was
        predicted (``predicted_area``, its pixels), the mask also covers at least ``min_predicted_area`` of the
        largest keyframe mask. A mostly hidden instrument's predicted mask is mostly the margin around the rendered
        model, where the fingers holding it lie at its depth; as a keyframe they would join the model."""
        if self.keyframes and rotation_gaps_deg(pose, self.poses()).min() < self.cfg.keyframe_rot_deg:
            return False
        return (predicted_area is None or not self.keyframes
                or predicted_area >= self.cfg.min_predicted_area * max(k.area for k in self.keyframes))

    def poses(self) -> np.ndarray:
        """The keyframes' poses, (n, 4, 4)."""
        return np.stack([k.pose for k in self.keyframes])

    def add(self, kf: Keyframe) -> None:
        self.keyframes.append(kf)
        if len(self.keyframes) > self.cfg.max_size:
            self.keyframes.pop(self._most_redundant())

    def _most_redundant(self) -> int:
        dirs = np.array([k.view_dir for k in self.keyframes])
        cos = np.clip(dirs @ dirs.T, -1, 1)
        np.fill_diagonal(cos, -1)
        nearest = cos.max(axis=1)
        nearest[0] = -np.inf  # the first keyframe anchors the object frame
        return int(np.argmax(nearest))

    def select(self, pose: np.ndarray, n: int, exclude: set[str] = frozenset(),
               within_deg: float | None = None) -> list[Keyframe]:
        """Up to n keyframes whose view overlaps the current one (optical axes within ``within_deg``, by default
        overlap_normal_deg), nearest in viewing direction first."""
        cands = [k for k in self.keyframes if k.frame_id not in exclude]
        if not cands:
            return []
        dirs = np.stack([k.view_dir for k in cands])
        ang = np.degrees(np.arccos(np.clip(dirs @ pose[2, :3], -1, 1)))
        order = np.argsort(ang)
        limit = self.cfg.overlap_normal_deg if within_deg is None else within_deg
        return [cands[i] for i in order if ang[i] <= limit][:n]
