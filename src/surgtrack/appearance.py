"""Appearance check of a pose hypothesis (re-localisation, Stage 2 step 5): do the frame's instrument pixels look,
in the keyframes that see them at that pose, as they look now?

Geometry alone cannot tell a round shaft from itself turned end for end; the markings can. The frame's points,
placed in a keyframe by the hypothesis, are compared by intensity with what the keyframe saw there: the normalised
cross-correlation (NCC) is high when the markings line up and near 0 or below when they do not. NCC is unchanged
by the light's gain and offset between the two views. Shading counts as much as markings, so on a dark shaft with
few markings the signal is weak: the check refuses clear mismatches, and only breaks ties otherwise.
"""

from __future__ import annotations

import cv2
import numpy as np

from .geometry import inv_T, project, transform
from .memory_pool import Keyframe


def intensity(rgb: np.ndarray) -> np.ndarray:
    """(H, W) uint8 grey image of an RGB frame."""
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def sample(image: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values of ``image`` at the nearest pixels of ``uv`` (N, 2) and which of them lie inside it."""
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = (u >= 0) & (u < image.shape[1]) & (v >= 0) & (v < image.shape[0])
    return image[np.where(inside, v, 0), np.where(inside, u, 0)], inside


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation of two equally long samples (0 when either is constant)."""
    a, b = a - a.mean(), b - b.mean()
    den = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b) / den if den > 0 else 0.0


def keyframe_ncc(points: np.ndarray, values: np.ndarray, pose: np.ndarray, kf: Keyframe, depth_tol: float,
                 min_points: int) -> float | None:
    """NCC of the frame's intensities ``values`` (N,) at its instrument ``points`` (N, 3, camera frame; the frame
    at object pose ``pose``) with keyframe ``kf``'s intensities where those points land in it: inside its mask and
    at its observed depth within ``depth_tol`` m (points it does not see are left out). None when it sees fewer
    than ``min_points`` of them, or has no image."""
    if kf.image is None:
        return None
    q = transform(kf.pose @ inv_T(pose), points)
    uv, _ = project(q, kf.K)
    seen, inside = sample(kf.image, uv)
    depth, _ = sample(kf.depth, uv)
    mask, _ = sample(kf.mask, uv)
    ok = inside & mask & (np.abs(depth - q[:, 2]) < depth_tol)
    if ok.sum() < min_points:
        return None
    return ncc(values[ok].astype(np.float64), seen[ok].astype(np.float64))
