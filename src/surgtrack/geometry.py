"""Rigid-body and camera geometry shared by every stage: SE(3) maps, pinhole projection, Kabsch."""

from __future__ import annotations

import numpy as np


def transform(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to an (N, 3) array of points."""
    return p @ T[:3, :3].T + T[:3, 3]


def rotate(T: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Apply the rotation of a 4x4 transform to an (N, 3) array of directions."""
    return n @ T[:3, :3].T


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Assemble a 4x4 transform from a rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R = T[:3, :3]
    return make_T(R.T, -R.T @ T[:3, 3])


def orthonormalize(T: np.ndarray) -> np.ndarray:
    """The nearest rigid transform (rotation projected onto SO(3) by SVD): stops round-off growing as poses
    are chained."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    return make_T(R, T[:3, 3])


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric matrix [w]_x of a 3-vector."""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotation matrix exp([w]_x)."""
    theta = float(np.linalg.norm(w))
    K = hat(w)
    if theta < 1e-10:
        return np.eye(3) + K
    return np.eye(3) + np.sin(theta) / theta * K + (1 - np.cos(theta)) / theta**2 * K @ K


def so3_log(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix (inverse of so3_exp)."""
    cos = np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)
    theta = np.arccos(cos)
    if theta < 1e-10:
        return np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / 2
    if np.pi - theta < 1e-6:
        # Near pi: axis from the largest diagonal of (R + I) / 2.
        M = (R + np.eye(3)) / 2
        axis = M[:, np.argmax(np.diag(M))]
        return axis / np.linalg.norm(axis) * theta
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * theta / (2 * np.sin(theta))


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """Small-increment SE(3) map for xi = (rho, phi): rotation exp(phi), translation rho (left update)."""
    return make_T(so3_exp(xi[3:]), xi[:3])


def is_rotation(R: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether a 3x3 matrix is a rotation (orthonormal, determinant +1)."""
    R = np.asarray(R, dtype=np.float64)
    return R.shape == (3, 3) and bool(np.allclose(R @ R.T, np.eye(3), atol=tol)) and np.linalg.det(R) > 0


def rotation_angle_deg(R: np.ndarray) -> float:
    """Geodesic angle of a rotation matrix, degrees."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def rotation_gaps_deg(T: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Geodesic angle of the relative rotation between pose ``T`` and each of ``poses`` (n, 4, 4), degrees, at once:
    trace(R R_k^T) is the sum of the elementwise product of the two rotations."""
    cos = ((T[None, :3, :3] * poses[:, :3, :3]).sum(axis=(1, 2)) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def kabsch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid T with dst ~ T @ src (Kabsch/Umeyama without scale), optional weights."""
    w = np.ones(len(src)) if w is None else w
    w = w / w.sum()
    cs, cd = w @ src, w @ dst
    H = (src - cs).T @ ((dst - cd) * w[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return make_T(R, cd - R @ cs)


def off_line(points: np.ndarray, centre: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Distances of ``points`` from the line through ``centre`` along the unit vector ``direction``."""
    q = points - centre
    return np.linalg.norm(q - np.outer(q @ direction, direction), axis=1)


def span(points: np.ndarray, share: float = 98.0) -> float:
    """How wide ``points`` spread (m): twice the ``share`` percentile of their distances from their median, a
    diameter that a few stray points do not set."""
    if len(points) == 0:
        return 0.0
    return 2.0 * float(np.percentile(np.linalg.norm(points - np.median(points, axis=0), axis=1), share))


def backproject(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points of valid depth pixels (inside mask): returns (N, 3) points and (N, 2) pixel (v, u)."""
    valid = depth > 0
    if mask is not None:
        valid &= mask
    v, u = np.nonzero(valid)
    z = depth[v, u]
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    return np.stack([x, y, z], axis=1), np.stack([v, u], axis=1)


def depth_to_xyz(depth: np.ndarray, K: np.ndarray, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """Per-pixel camera-frame points (H, W, 3) of a depth map, or of a crop of one whose top-left pixel is
    ``origin`` = (row, column) in the image K belongs to; invalid pixels have z = 0."""
    return np.stack([*depth_to_xy(depth, K, origin), depth], axis=-1)


def depth_to_xy(depth: np.ndarray, K: np.ndarray, origin: tuple[int, int] = (0, 0)) -> tuple[np.ndarray, np.ndarray]:
    """The x and y planes (H, W) of `depth_to_xyz` (its z plane is ``depth``), in float64."""
    h, w = depth.shape
    x = (np.arange(origin[1], origin[1] + w) - K[0, 2]) * depth / K[0, 0]
    y = (np.arange(origin[0], origin[0] + h)[:, None] - K[1, 2]) * depth / K[1, 1]
    return x, y


def project(p: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of camera-frame points: (N, 2) pixel (u, v) and (N,) depth z."""
    z = p[:, 2]
    zs = np.where(np.abs(z) < 1e-9, 1e-9, z)
    u = K[0, 0] * p[:, 0] / zs + K[0, 2]
    v = K[1, 1] * p[:, 1] / zs + K[1, 2]
    return np.stack([u, v], axis=1), z


def voxel_downsample(p: np.ndarray, voxel: float) -> np.ndarray:
    """One point (the first) per occupied voxel of edge ``voxel``."""
    if len(p) == 0:
        return p
    keys = np.floor(p / voxel).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:  # one int64 per voxel: 8x faster than rows
        _, first = np.unique((keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2], return_index=True)
    else:
        _, first = np.unique(keys, axis=0, return_index=True)
    return p[np.sort(first)]
