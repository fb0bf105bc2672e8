"""Instrument masks for frames that come without one: render the model at the predicted pose, keep the pixels whose
observed depth agrees, and leave out occluders in front."""

from __future__ import annotations

import cv2
import numpy as np

from .geometry import project, transform


def render_depth(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, shape: tuple[int, int],
                 splat: int = 2) -> np.ndarray:
    """Z-buffered depth of model points seen at ``pose`` (0 where nothing projects); points are splatted to
    (2 * splat + 1)^2 pixels so a sparse model renders as a closed surface."""
    h, w = shape
    p = transform(pose, points_obj)
    p = p[p[:, 2] > 1e-3]
    uv, z = project(p, K)
    u = np.round(uv[:, 0]).astype(int)
    v = np.round(uv[:, 1]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[inside], v[inside], z[inside]
    depth = np.full((h, w), np.inf, np.float32)
    np.minimum.at(depth, (v, u), z.astype(np.float32))
    if splat > 0:
        depth = -cv2.dilate(-depth, np.ones((2 * splat + 1,) * 2, np.uint8))  # min filter
    depth[depth >= np.finfo(np.float32).max] = 0  # the min filter pads the border with float32 max
    depth[~np.isfinite(depth)] = 0
    return depth


def predict_mask(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, depth: np.ndarray,
                 margin: int, tol: float) -> np.ndarray:
    """Mask of the instrument at a predicted pose: observed depth within ``tol`` of the model's depth nearby.

    The model depth is spread over ``margin`` pixels to absorb the prediction's error; observed depth more than
    ``tol`` in front of the model (an occluder) or behind it (background) is left out."""
    model = render_depth(points_obj, pose, K, depth.shape)
    if not (model > 0).any():
        return np.zeros(depth.shape, bool)
    near = np.where(model > 0, model, 0).astype(np.float32)
    far = np.where(model > 0, model, 0).astype(np.float32)
    kernel = np.ones((2 * margin + 1,) * 2, np.uint8)
    big = np.float32(1e3)
    zmin = -cv2.dilate(-np.where(near > 0, near, big), kernel)
    zmax = cv2.dilate(far, kernel)
    covered = zmax > 0
    return covered & (depth > 0) & (depth > zmin - tol) & (depth < zmax + tol)
