"""Coarse pose by RANSAC over 3-point rigid hypotheses, refined by Kabsch on the inliers (paper eq. 5).

The paper's coarse pose (its eq. 5 in the compiled numbering; DESIGN.md calls it eq. 4) is
``argmin_{R,t} sum_i ||R p_i + t - q_i||^2`` over matched 3D points, made robust by RANSAC. Every hypothesis is
solved and scored at once: one batched SVD over (H, 3, 3) cross-covariances, and the (H, N) residuals expanded into
matrix products so that 2000 hypotheses x 500 matches cost a few milliseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations
from math import comb

import numpy as np

from surgtrack.config import RansacConfig
from surgtrack.geometry import kabsch, make_T, rotation_angle_deg

_CHUNK_ELEMENTS = 2_000_000  # hypotheses x matches scored per block, bounding memory for large match sets


@dataclass
class RansacResult:
    """Outcome of `ransac_pose`: ``T`` maps src to dst (dst ~ T @ src), or is None on failure."""

    T: np.ndarray | None
    inliers: np.ndarray  # (N,) bool
    n_inliers: int
    rmse: float  # m, over the inliers of T (inf on failure)

    @property
    def ok(self) -> bool:
        return self.T is not None


def _failure(n: int, inliers: np.ndarray | None = None) -> RansacResult:
    mask = np.zeros(n, dtype=bool) if inliers is None else inliers
    return RansacResult(T=None, inliers=mask, n_inliers=int(mask.sum()), rmse=float("inf"))


@lru_cache(maxsize=64)
def _all_triples(n: int) -> np.ndarray:
    """Every unordered 3-point sample of n matches, (comb(n, 3), 3), read-only (it is shared)."""
    triples = np.array(list(combinations(range(n), 3)), dtype=np.int64).reshape(-1, 3)
    triples.setflags(write=False)
    return triples


def _samples(n: int, hypotheses: int, rng: np.random.Generator) -> np.ndarray:
    """3-point samples (H, 3): every unordered triple when there are at most ``hypotheses`` of them (the search is
    then exhaustive, and random draws would only repeat triples), else ``hypotheses`` random draws."""
    if comb(n, 3) <= hypotheses:
        return _all_triples(n)
    return rng.integers(0, n, size=(hypotheses, 3))


def _lengths(v: np.ndarray) -> np.ndarray:
    """Euclidean norm along the last axis of (..., 3), as np.linalg.norm computes it, without its per-call cost."""
    return np.sqrt(v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2])


def _spread_and_sides(P: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """For triangles P (H, 3, 3): the height over the longest side (0 for collinear or coincident points) and the
    side lengths |P0 - P1|, |P0 - P2|, |P1 - P2|."""
    a, b, c = P[:, 0], P[:, 1], P[:, 2]
    u, v = b - a, c - a
    cross = np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1], u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                      u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], axis=-1)
    sides = [_lengths(u), _lengths(v), _lengths(c - b)]
    longest = np.maximum(np.maximum(sides[0], sides[1]), sides[2])
    return _lengths(cross) / np.maximum(longest, 1e-12), sides


def _batched_kabsch(S: np.ndarray, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid (R, t) with D ~ R S + t for every hypothesis: S, D (H, k, 3) -> R (H, 3, 3), t (H, 3)."""
    cs, cd = S.mean(axis=1), D.mean(axis=1)
    C = np.einsum("hki,hkj->hij", S - cs[:, None], D - cd[:, None])
    U, _, Vt = np.linalg.svd(C)
    V = Vt.transpose(0, 2, 1)
    d = np.sign(np.linalg.det(V @ U.transpose(0, 2, 1)))
    V[:, :, 2] *= d[:, None]
    R = V @ U.transpose(0, 2, 1)
    t = cd - np.einsum("hij,hj->hi", R, cs)
    return R, t


def _score(
    R: np.ndarray,
    t: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    ds: np.ndarray,
    nn: np.ndarray | None,
    thr2: float,
    cos_thr: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Inlier count and mean inlier squared residual of each hypothesis, without forming (H, N, 3) arrays.

    ``|R s + t - d|^2 = |s|^2 + |d|^2 + |t|^2 - 2 t.d + 2 (R^T t).s - 2 vec(R).(d kron s)``; the normal test uses
    ``(R n_s).n_d = vec(R).(n_d kron n_s)``.
    """
    H = len(R)
    R9 = R.reshape(H, 9)
    d2 = R9 @ ds.T
    d2 *= -2.0
    d2 += (2.0 * np.einsum("hij,hi->hj", R, t)) @ src.T
    d2 -= (2.0 * t) @ dst.T
    d2 += (t * t).sum(1)[:, None]
    d2 += (src * src).sum(1)[None] + (dst * dst).sum(1)[None]
    inl = d2 < thr2
    if nn is not None:
        inl &= (R9 @ nn.T) > cos_thr
    count = inl.sum(axis=1)
    resid = np.where(inl, d2, 0.0).sum(axis=1) / np.maximum(count, 1)
    return count, resid


def _inliers_of(
    T: np.ndarray,
    src: np.ndarray,
    dst: np.ndarray,
    src_n: np.ndarray | None,
    dst_n: np.ndarray | None,
    thr: float,
    cos_thr: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Inlier mask of a single transform and the residual distance of every match."""
    r = _lengths(src @ T[:3, :3].T + T[:3, 3] - dst)
    inl = r < thr
    if src_n is not None and dst_n is not None:
        inl &= np.einsum("ij,ij->i", src_n @ T[:3, :3].T, dst_n) > cos_thr
    return inl, r


def ransac_pose(
    src: np.ndarray,
    dst: np.ndarray,
    cfg: RansacConfig,
    rng: np.random.Generator,
    src_n: np.ndarray | None = None,
    dst_n: np.ndarray | None = None,
) -> RansacResult:
    """Robust rigid T with dst ~ T @ src from matched 3D points (paper eq. 5).

    ``cfg.hypotheses`` 3-point samples are drawn, or every triple when there are no more than that (`_samples`);
    samples whose triangle is lower than ``cfg.min_sample_spread`` in either frame, or whose pairwise distances
    disagree between frames by more than ``2 * cfg.inlier_dist`` (they cannot all be inliers), are discarded. A match
    is an inlier when its residual is below ``cfg.inlier_dist`` and, with normals given for both sides, the rotated
    source normal lies within ``cfg.inlier_normal_deg`` of the destination normal. The hypothesis with most inliers
    (ties: smallest mean squared inlier residual) is refitted by Kabsch on its inliers ``cfg.refits`` times. Fewer
    than 3 matches, no valid sample, or fewer than ``cfg.min_inliers`` inliers returns ``T = None``.
    """
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if len(src) != len(dst):
        raise ValueError(f"src and dst differ in length: {len(src)} vs {len(dst)}")
    n = len(src)
    use_n = src_n is not None and dst_n is not None
    if use_n:
        src_n = np.asarray(src_n, dtype=np.float64).reshape(-1, 3)
        dst_n = np.asarray(dst_n, dtype=np.float64).reshape(-1, 3)
    else:
        src_n = dst_n = None
    if n < 3:
        return _failure(n)

    thr = float(cfg.inlier_dist)
    cos_thr = float(np.cos(np.radians(cfg.inlier_normal_deg)))
    # Centre both clouds: smaller magnitudes keep the expanded residuals of `_score` accurate.
    cs0, cd0 = src.mean(axis=0), dst.mean(axis=0)
    s, d = src - cs0, dst - cd0

    idx = _samples(n, cfg.hypotheses, rng)
    S, D = s[idx], d[idx]
    hs, ls = _spread_and_sides(S)
    hd, ld = _spread_and_sides(D)
    valid = (hs >= cfg.min_sample_spread) & (hd >= cfg.min_sample_spread)
    for k in range(3):
        valid &= np.abs(ls[k] - ld[k]) < 2.0 * thr
    if not valid.any():
        return _failure(n)
    S, D = S[valid], D[valid]
    R, t = _batched_kabsch(S, D)

    ds = (d[:, :, None] * s[:, None, :]).reshape(n, 9)
    nn = (dst_n[:, :, None] * src_n[:, None, :]).reshape(n, 9) if use_n else None
    chunk = max(1, _CHUNK_ELEMENTS // n)
    counts, resids = [], []
    for k in range(0, len(R), chunk):
        c, r = _score(R[k : k + chunk], t[k : k + chunk], s, d, ds, nn, thr * thr, cos_thr)
        counts.append(c)
        resids.append(r)
    count, resid = np.concatenate(counts), np.concatenate(resids)
    best = int(np.lexsort((resid, -count))[0])
    if count[best] < 3:
        return _failure(n)

    T = make_T(R[best], t[best])
    inl, r = _inliers_of(T, s, d, src_n, dst_n, thr, cos_thr)
    for _ in range(cfg.refits):
        if inl.sum() < 3:
            break
        T_new = kabsch(s[inl], d[inl])
        inl_new, r_new = _inliers_of(T_new, s, d, src_n, dst_n, thr, cos_thr)
        if inl_new.sum() < inl.sum():
            break
        T, inl, r = T_new, inl_new, r_new
    n_inl = int(inl.sum())
    if n_inl < max(cfg.min_inliers, 3):
        return _failure(n, inl)
    T_full = make_T(np.eye(3), cd0) @ T @ make_T(np.eye(3), -cs0)
    return RansacResult(T=T_full, inliers=inl, n_inliers=n_inl, rmse=float(np.sqrt(np.mean(r[inl] ** 2))))


def within(T: np.ndarray, trans: float, rot_deg: float) -> bool:
    """Whether the 4x4 motion ``T`` is finite, moves at most ``trans`` (m, translation norm) and turns at most
    ``rot_deg`` degrees."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    return bool(np.linalg.norm(T[:3, 3]) <= trans and rotation_angle_deg(T[:3, :3]) <= rot_deg)


def plausible(T_prev_to_cur: np.ndarray, cfg: RansacConfig) -> bool:
    """False for a frame-to-frame motion beyond the physical bounds of ``cfg`` (translation norm of the 4x4 motion
    above ``cfg.max_jump_trans`` or rotation above ``cfg.max_jump_rot_deg``) or a non-finite transform."""
    return within(T_prev_to_cur, cfg.max_jump_trans, cfg.max_jump_rot_deg)
