"""Overlay frames and video: the model's outline and axes drawn at the tracked pose, lost frames marked."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .geometry import project, transform
from .masking import render_depth

if TYPE_CHECKING:
    from .io import Frame
    from .tracker import TrackResult


def draw_overlay(rgb: np.ndarray, pose: np.ndarray | None, K: np.ndarray, points_obj: np.ndarray,
                 status: str, axis_len: float = 0.03, reason: str = "",
                 unmeasured: Sequence[str] = (), colour: float | None = None) -> np.ndarray:
    """RGB frame with the model's silhouette outline (green) and object axes at ``pose``; lost frames say so, and
    why (``reason``, `TrackResult.reason`); a posed frame names what its data left unmeasured (``unmeasured``,
    `TrackResult.unmeasured_kinds`: "turn unmeasured" on a round shaft) and, tracked on a mask the tracker made,
    how instrument-like that mask looks (``colour``, `TrackResult.colour`)."""
    img = rgb.copy()
    if pose is None:
        cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), (255, 0, 0), 6)
        label = f"LOST: {reason}" if reason else "LOST"
        cv2.putText(img, label, (12, 36), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 0, 0), 2, cv2.LINE_AA)
        return img
    sil = (render_depth(points_obj, pose, K, rgb.shape[:2]) > 0).astype(np.uint8)
    contours, _ = cv2.findContours(sil, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    cv2.drawContours(img, contours, -1, (0, 255, 0), 2, cv2.LINE_AA)
    axes = np.array([[0, 0, 0], [axis_len, 0, 0], [0, axis_len, 0], [0, 0, axis_len]])
    uv, z = project(transform(pose, axes), K)
    if np.all(z > 0):
        o = tuple(int(x) for x in uv[0])
        for k, axis_colour in zip(range(1, 4), [(255, 0, 0), (0, 255, 0), (0, 0, 255)], strict=True):
            cv2.line(img, o, tuple(int(x) for x in uv[k]), axis_colour, 2, cv2.LINE_AA)
    made = [] if colour is None else [f"colour {colour:.2f}"]
    label = ", ".join([status] + [f"{k} unmeasured" for k in unmeasured] + made)
    cv2.putText(img, label, (12, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA)
    return img


def draw_result(frame: Frame, result: TrackResult, points_obj: np.ndarray | None) -> np.ndarray:
    """`draw_overlay` of a tracked ``frame`` with all its ``result`` says, the model's points ``points_obj`` (the
    tracker's `model_points`; None before it has any) outlined at its pose."""
    points = points_obj if points_obj is not None else np.zeros((0, 3))
    return draw_overlay(frame.rgb, result.pose, frame.K, points, result.status, reason=result.reason,
                        unmeasured=result.unmeasured_kinds, colour=result.colour)


class OverlayVideo:
    """MP4 of overlay frames (OpenCV's mp4v codec)."""

    def __init__(self, path: Path | str, size: tuple[int, int], fps: float = 15.0):
        self.path = Path(path)
        self._writer = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
        if not self._writer.isOpened():
            raise OSError(f"{self.path}: cannot open a video writer")

    def write(self, rgb: np.ndarray) -> None:
        self._writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))

    def close(self) -> None:
        self._writer.release()
