"""Posture graph optimisation (paper eqs. 7-11): robust Gauss-Newton over the SE(3) poses of the graph's nodes.

The graph G = (V, E) (eq. 7) holds the current frame and frames chosen from the posture memory pool (eq. 6). Its
poses minimise the energy of eq. 8,

    w_s L_SDF(t) + sum_{i != j} [ w_f L_3D(i, j) + w_p L_2D(i, j) ],

with L_3D the matched-feature distance in the object frame (eq. 9), L_2D the projective point-to-plane distance
(eq. 10) and L_SDF the signed distance of the current frame's points to the instrument surface (eq. 11), every term
under the Huber loss rho. Optionally (not in the paper) w_fs L_FS(t): the model's points that the current frame saw
past, into the background, pulled back inside the frame's mask (`FreeSpace`); and w_cv L_CV(t): the frame's
points that the first keyframe saw past, pulled back inside its mask (`Coverage`).

Parametrisation: each node's camera-in-object pose C_i = pose_i^-1 receives a left increment,
C_i <- exp(delta_i) C_i with delta_i = (rho, phi) and `geometry.se3_exp` (translation rho, rotation exp(phi)); this
is a right increment exp(-delta_i) of pose_i. Every residual lives in the object frame, where a point y = C_i p moves
by rho + phi x y, so each Jacobian block is [I, -[y]_x] or a projection of it. The Huber loss is minimised by
iteratively re-weighted least squares (weight min(1, delta / |r|)); the dense 6n x 6n normal equations, with the
fixed nodes' rows and columns removed and a small Levenberg-Marquardt damping, are solved each iteration after L_2D
has been re-associated.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from surgtrack.config import GraphConfig
from surgtrack.geometry import inv_T, project, se3_exp, so3_log
from surgtrack.preprocess import MaskEdge

SDFFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class GridPoints:
    """A grid's valid pixels (z > 0, finite, with a unit normal): flat pixel indices ``idx`` (N,), camera-frame
    points ``p`` and unit normals ``q`` (N, 3), the pixels' bounding ``box`` (top row, left column, rows, columns)
    and ``lut``, 1 + each box pixel's row in them (0: none), row-major over the box. A keyframe joins many solves;
    its points are found once (`of`) and handed over with each `GraphNode`."""

    idx: np.ndarray
    p: np.ndarray
    q: np.ndarray
    box: tuple[int, int, int, int]
    lut: np.ndarray

    @classmethod
    def of(cls, xyz: np.ndarray, normals: np.ndarray) -> GridPoints:
        w = xyz.shape[1]
        xyz = np.asarray(xyz).reshape(-1, 3)
        idx = np.flatnonzero(xyz[:, 2] > 0)
        p = xyz[idx].astype(np.float64)
        q = np.asarray(normals).reshape(-1, 3)[idx].astype(np.float64)
        qn = np.linalg.norm(q, axis=1)
        ok = np.isfinite(p).all(1) & np.isfinite(qn) & (qn > 0.5)
        idx, p, q = idx[ok], p[ok], q[ok] / qn[ok, None]
        if len(idx) == 0:
            return cls(idx, p, q, (0, 0, 0, 0), np.zeros(0, dtype=np.int32))
        v, u = np.divmod(idx, w)
        box = (int(v.min()), int(u.min()), int(v.max() - v.min()) + 1, int(u.max() - u.min()) + 1)
        lut = np.zeros(box[2] * box[3], dtype=np.int32)
        lut[(v - box[0]) * box[3] + u - box[1]] = np.arange(1, len(idx) + 1, dtype=np.int32)
        return cls(idx, p, q, box, lut)


@dataclass
class GraphNode:
    """One frame of the posture graph: pose and its depth at the association resolution."""

    pose: np.ndarray  # 4x4 object-to-camera (x_cam = pose @ x_obj)
    xyz: np.ndarray  # (h, w, 3) camera-frame points; z = 0 where invalid or outside the instrument
    normals: np.ndarray  # (h, w, 3) camera-frame unit normals on the same grid
    K: np.ndarray  # 3x3 intrinsics scaled to that grid
    fixed: bool = False
    points: GridPoints | None = None  # `GridPoints.of(xyz, normals)`, when the caller keeps it; made when None

    def grid_points(self) -> GridPoints:
        return self.points if self.points is not None else GridPoints.of(self.xyz, self.normals)


@dataclass
class FeatureEdge:
    """Matched features C_ij between nodes i and j (eq. 9): p_i[k] and p_j[k] are the same surface point."""

    i: int
    j: int
    p_i: np.ndarray  # (M, 3) in node i's camera frame
    p_j: np.ndarray  # (M, 3) in node j's camera frame


@dataclass(frozen=True)
class MaskView:
    """A frame's instrument mask with its edge (`preprocess.MaskEdge`), its depth and intrinsics: what it saw past,
    for L_FS (the current frame's) and L_CV (a keyframe's)."""

    edge: MaskEdge  # the frame's mask and its edge pixels
    depth: np.ndarray  # (H, W) metres, 0 = invalid
    K: np.ndarray  # 3x3

    @classmethod
    def of(cls, edge: MaskEdge, depth: np.ndarray, K: np.ndarray) -> MaskView:
        """The view of a frame's mask edge, its depth (as float32) and intrinsics (as float64)."""
        return cls(edge, np.asarray(depth, dtype=np.float32), np.asarray(K, dtype=np.float64))

    def seen_past(self, y: np.ndarray, C: np.ndarray, cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Which of the object-frame points ``y`` this view, at the camera-in-object pose C, saw past: their rows k,
        residuals r and gradients g = d r / d y (3, M) in the object frame.

        A point seen at x = C^-1 y, pixel (u, v), is in free space where the view's depth at that pixel lies more
        than ``cfg.free_space_tol`` behind it (it saw past the point, not an occluder in front of it) and (u, v) is
        more than ``cfg.free_space_margin`` pixels from the mask; then r = (dist(u, v) - margin) z / f_x, its
        distance to the mask in metres at the point's depth (z / f_x held constant in the gradient)."""
        (fx, _, cx), (_, fy, cy) = self.K[0], self.K[1]
        h, w = self.depth.shape
        uv, z = project((y - C[:3, 3]) @ C[:3, :3], self.K)  # x = R_C^T (y - t_C)
        u, v = uv.T
        k = np.flatnonzero((z > 1e-6) & (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5))
        z, u, v = z[k], u[k], v[k]
        px = (v + 0.5).astype(np.int64) * w + (u + 0.5).astype(np.int64)
        seen = ~self.edge.mask.ravel()[px] & (self.depth.ravel()[px] > z + cfg.free_space_tol)  # NaN: not seen
        if not seen.any():
            return np.zeros(0, np.int64), np.zeros(0), np.zeros((3, 0))
        k, z, u, v = k[seen], z[seen], u[seen], v[seen]
        dist, gu, gv = self.edge.distance(u, v)
        free = dist > cfg.free_space_margin
        k, z, u, v, gu, gv = k[free], z[free], u[free], v[free], gu[free], gv[free]
        s = z / fx
        g = C[:3, :3] @ (np.stack([gu * fx, gv * fy, -(gu * (u - cx) + gv * (v - cy))]) * (s / z))  # (3, M)
        return k, (dist[free] - cfg.free_space_margin) * s, g


@dataclass(frozen=True)
class FreeSpace:
    """What the current frame saw past the instrument, for L_FS: the model's points (object frame) and the frame's
    `MaskView`."""

    points: np.ndarray  # (N, 3) object frame
    view: MaskView  # the current frame's mask, depth and intrinsics

    @classmethod
    def of(cls, points: np.ndarray, edge: MaskEdge, depth: np.ndarray, K: np.ndarray, cap: int) -> FreeSpace:
        """At most ``cap`` of ``points`` (strided) against the frame's mask (`preprocess.MaskEdge`) and its
        ``depth``."""
        return cls(strided(points, cap), MaskView.of(edge, depth, K))

    def residuals(self, C: np.ndarray, cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray]:
        """L_FS at the camera-in-object pose C: residuals r (M,) and Jacobians (6, M) on the left increment delta,
        for the M model points this frame saw past (`MaskView.seen_past`; every other point's residual is 0). The
        increment moves a model point y by -(rho + phi x y) relative to the camera, so dr/d delta = [-g, g x y]."""
        k, r, g = self.view.seen_past(self.points, C, cfg)
        J = np.empty((6, len(k)))
        J[:3] = -g
        _cross(g[None], self.points[k].T[None], J[None, 3:])
        return r, J


@dataclass(frozen=True)
class Coverage:
    """What a keyframe saw past, for L_CV: the current frame's points (camera frame), and the keyframe's `MaskView`
    with its camera-in-object pose. The counterpart of L_FS: that keeps the model out of what the frame saw past,
    this keeps the frame's points out of what the keyframe saw past, so a shaft slid along itself is held by
    whichever of its ends the keyframe saw with background beyond it."""

    points: np.ndarray  # (N, 3) current camera frame
    view: MaskView  # the keyframe's mask, depth and intrinsics
    C_view: np.ndarray  # 4x4 the keyframe's camera-in-object pose

    @classmethod
    def of(cls, points: np.ndarray, view: MaskView, C_view: np.ndarray, cap: int) -> Coverage:
        """At most ``cap`` of the frame's ``points`` (strided) against the keyframe's ``view`` at ``C_view``."""
        return cls(strided(points, cap), view, np.asarray(C_view, dtype=np.float64))

    def residuals(self, C: np.ndarray, cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray]:
        """L_CV at the current frame's camera-in-object pose C: residuals r (M,) and Jacobians (6, M) on the left
        increment delta, for the M points y = C x the keyframe saw past (`MaskView.seen_past`) by at most
        ``cfg.coverage_gate``: a point further in stands there because the pose is wrong across the board, not
        slid, and pulling it in would not mend that. The increment moves y by rho + phi x y, so
        dr/d delta = [g, y x g]."""
        y = self.points @ C[:3, :3].T + C[:3, 3]
        k, r, g = self.view.seen_past(y, self.C_view, cfg)
        near = r <= cfg.coverage_gate
        k, r, g = k[near], r[near], g[:, near]
        J = np.empty((6, len(k)))
        J[:3] = g
        _cross(y[k].T[None], g[None], J[None, 3:])
        return r, J


def strided(points: np.ndarray, cap: int) -> np.ndarray:
    """At most ``cap`` of ``points`` (all when ``cap`` <= 0), taken on an even stride, as float64."""
    step = int(np.ceil(len(points) / cap)) if 0 < cap < len(points) else 1
    return np.asarray(points[::step], dtype=np.float64)


def huber_weight(r: np.ndarray, delta: float) -> np.ndarray:
    """IRLS weight of the Huber loss rho: 1 inside |r| <= delta, delta / |r| outside."""
    return delta / np.maximum(np.abs(r), delta)


def _cross(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Cross product of component-major (G, 3, m) arrays along axis 1, written to ``out`` (G, 3, m)."""
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _inv_batch(T: np.ndarray) -> np.ndarray:
    """Inverses of rigid (n, 4, 4) transforms."""
    out = np.zeros_like(T)
    Rt = T[:, :3, :3].transpose(0, 2, 1)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


class _Normal:
    """Block normal equations (sum w J^T J) delta = -(sum w J^T r) of one re-weighted Gauss-Newton step.

    Residual groups are component-major: Jacobians (G, 6, m), residuals and weights (G, m), node ids (G,).
    """

    def __init__(self, n: int) -> None:
        self.H = np.zeros((n, n, 6, 6))
        self.g = np.zeros((n, 6))

    def add(
        self,
        a: np.ndarray,
        Ja: np.ndarray,
        r: np.ndarray,
        w: np.ndarray,
        b: np.ndarray | None = None,
        Jb: np.ndarray | None = None,
    ) -> None:
        """Residuals on node a (Jacobian Ja) and, when given, node b (Jacobian Jb)."""
        wJa = Ja * w[:, None, :]
        np.add.at(self.H, (a, a), np.matmul(wJa, Ja.transpose(0, 2, 1)))
        np.add.at(self.g, a, np.matmul(wJa, r[..., None])[..., 0])
        if b is None or Jb is None:
            return
        wJb = Jb * w[:, None, :]
        Hab = np.matmul(wJa, Jb.transpose(0, 2, 1))
        np.add.at(self.H, (a, b), Hab)
        np.add.at(self.H, (b, a), Hab.transpose(0, 2, 1))
        np.add.at(self.H, (b, b), np.matmul(wJb, Jb.transpose(0, 2, 1)))
        np.add.at(self.g, b, np.matmul(wJb, r[..., None])[..., 0])

    def add_opposed(self, a: np.ndarray, b: np.ndarray, A: np.ndarray, gv: np.ndarray) -> None:
        """Groups with Jacobian J on node b and -J on node a, given A = J^T W J (G, 6, 6) and gv = J^T W r (G, 6)."""
        np.add.at(self.H, (a, a), A)
        np.add.at(self.H, (b, b), A)
        np.add.at(self.H, (a, b), -A)
        np.add.at(self.H, (b, a), -A)
        np.add.at(self.g, a, -gv)
        np.add.at(self.g, b, gv)

    def solve(self, free: np.ndarray, damping: float) -> np.ndarray:
        """Damped step delta (n, 6); fixed nodes get zero."""
        n = len(self.g)
        H = self.H.transpose(0, 2, 1, 3).reshape(6 * n, 6 * n)
        sel = np.repeat(free, 6)
        Hf = H[np.ix_(sel, sel)]
        gf = self.g.reshape(-1)[sel]
        d = np.diag(Hf).copy()
        Hf[np.diag_indices_from(Hf)] += damping * d + 1e-12 * max(float(d.max(initial=0.0)), 1.0)
        try:
            step = np.linalg.solve(Hf, -gf)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(Hf, -gf, rcond=None)[0]
        delta = np.zeros(6 * n)
        delta[sel] = step
        return delta.reshape(n, 6)


class _NodeData:
    """Per-node point samples (sources of L_2D and L_SDF) and a pixel lookup of every valid point (targets of L_2D).

    Samples are strided down to at most ``cap`` per node and padded to a common length m: homogeneous points
    ``ph`` (n, 4, m), unit normals ``nrm`` (n, 3, m), mask ``mask`` (n, m), all in each node's camera frame. Targets:
    ``lut`` maps node k's pixel (v, u) inside its box (`GridPoints`) at ``base[k] + (v - top[k]) * w[k] + u -
    left[k]`` to 1 + the row of its point among node k's (0: none), which is column that + ``shift[k]`` of ``tx`` /
    ``tn`` (3, 1 + N); column 0 is an empty target with z = 0. The nodes' own lookups are concatenated as they are.
    """

    def __init__(self, nodes: Sequence[GraphNode], cap: int) -> None:
        valid = [nd.grid_points() for nd in nodes]
        self.top, self.left, self.h, self.w = np.array([g.box for g in valid], dtype=np.int64).reshape(-1, 4).T
        self.base = np.concatenate([[0], np.cumsum(self.h * self.w)[:-1]])
        counts = np.array([len(g.p) for g in valid])
        first = 1 + np.concatenate([[0], np.cumsum(counts)[:-1]])
        self.lut = np.concatenate([g.lut for g in valid] + [np.zeros(1, np.int32)])  # a 0 at the end: never empty
        self.shift = first - 1  # node k's points start at column 1 + shift[k] of tx, tn
        self.tx = np.zeros((3, 1 + int(counts.sum())))
        self.tx[:, 1:] = np.concatenate([g.p for g in valid]).T
        self.tn = np.zeros_like(self.tx)
        self.tn[:, 1:] = np.concatenate([g.q for g in valid]).T
        picks = [(strided(g.p, cap), strided(g.q, cap)) for g in valid]
        m = max(1, max(len(p) for p, _ in picks))
        self.ph = np.zeros((len(nodes), 4, m))
        self.ph[:, 3] = 1.0
        self.nrm = np.zeros((len(nodes), 3, m))
        self.mask = np.zeros((len(nodes), m), dtype=bool)
        for k, (p, q) in enumerate(picks):
            self.ph[k, :3, : len(p)] = p.T
            self.nrm[k, :, : len(p)] = q.T
            self.mask[k, : len(p)] = True


class _Projective:
    """L_2D (eq. 10) by projective association, for directed node pairs (i, j) = (pa[k], pb[k]).

    The residual n_i(p) . (T_ij^-1 x_j - p) is evaluated in camera j as n . (x_j - q), q = T_ij p, n the source
    normal rotated into camera j. In the object frame its Jacobian is [n_o, y_j x n_o] on delta_j and the negative on
    delta_i; it is formed in camera j as J = [n, x_j x n] and mapped by Ad = [[R, 0], [[t]_x R, R]] of C_j = (R, t).
    The per-pixel work runs in float32 (sub-micrometre rounding at camera distances); the 6 x 6 blocks are float64.
    """

    def __init__(self, data: _NodeData, nodes: Sequence[GraphNode], pairs: Sequence[tuple[int, int]], cfg: GraphConfig):
        f32 = np.float32
        self.pa = np.array([p[0] for p in pairs], dtype=int)
        self.pb = np.array([p[1] for p in pairs], dtype=int)
        pb = self.pb
        Ks = np.stack([np.asarray(nd.K, dtype=np.float64) for nd in nodes])[pb]
        self.fx, self.fy = Ks[:, 0, 0, None].astype(f32), Ks[:, 1, 1, None].astype(f32)
        self.cx, self.cy = (Ks[:, 0, 2, None] + 0.5).astype(f32), (Ks[:, 1, 2, None] + 0.5).astype(f32)
        self.v0, self.u0 = data.top[pb][:, None], data.left[pb][:, None]
        self.v1, self.u1 = self.v0 + data.h[pb][:, None], self.u0 + data.w[pb][:, None]
        self.wb = data.w[pb][:, None]
        self.base = (data.base[pb] - data.top[pb] * data.w[pb] - data.left[pb])[:, None]
        self.lut, self.shift = data.lut, data.shift[pb][:, None]
        self.tx, self.tn = data.tx.astype(f32), data.tn.astype(f32)
        self.ph_a = data.ph[self.pa].astype(f32)
        self.nrm_a = data.nrm[self.pa].astype(f32)
        self.smask = data.mask[self.pa]
        self.d2max = float(cfg.assoc_dist) ** 2
        self.cos = float(np.cos(np.radians(cfg.assoc_normal_deg)))
        self.delta, self.weight = float(cfg.huber_delta), float(cfg.w_p)
        self.B = np.empty((len(pairs), 6, data.ph.shape[2]), dtype=f32)
        self.Ad = np.zeros((len(pairs), 6, 6))

    def add_to(self, ne: _Normal, C: np.ndarray) -> None:
        """Associate with the current camera-in-object poses C (n, 4, 4) and add the re-weighted normal equations."""
        pa, pb = self.pa, self.pb
        Tba = np.matmul(_inv_batch(C[pb]), C[pa]).astype(np.float32)
        Q = np.matmul(Tba[:, :3, :], self.ph_a)
        Nq = np.matmul(Tba[:, :3, :3], self.nrm_a)
        z = Q[:, 2]
        front = self.smask & (z > 1e-6)
        iz = 1.0 / np.where(front, z, np.float32(1.0))
        uf = Q[:, 0] * iz
        uf *= self.fx
        uf += self.cx
        vf = Q[:, 1] * iz
        vf *= self.fy
        vf += self.cy
        ok = front & (uf >= self.u0) & (uf < self.u1) & (vf >= self.v0) & (vf < self.v1)  # in node b's box
        li = self.lut[np.where(ok, vf.astype(np.int64) * self.wb + uf.astype(np.int64) + self.base, 0)]
        ok &= li > 0
        li = np.where(ok, li + self.shift, 0)
        X = np.take(self.tx, li, axis=1)
        Nt = np.take(self.tn, li, axis=1)
        D = X - Q.transpose(1, 0, 2)
        NqT = Nq.transpose(1, 0, 2)
        ok &= np.einsum("kpm,kpm->pm", D, D) < self.d2max
        ok &= np.einsum("kpm,kpm->pm", NqT, Nt) > self.cos
        r = np.where(ok, np.einsum("kpm,kpm->pm", NqT, D), np.float32(0.0))
        sw = np.sqrt(self.weight * huber_weight(r, self.delta) * ok).astype(np.float32)
        B = self.B
        for k in range(3):
            np.multiply(Nq[:, k], sw, out=B[:, k])
        x0, x1, x2 = X[0], X[1], X[2]
        n0, n1, n2 = Nq[:, 0], Nq[:, 1], Nq[:, 2]
        np.multiply(x1 * n2 - x2 * n1, sw, out=B[:, 3])
        np.multiply(x2 * n0 - x0 * n2, sw, out=B[:, 4])
        np.multiply(x0 * n1 - x1 * n0, sw, out=B[:, 5])
        A = np.matmul(B, B.transpose(0, 2, 1)).astype(np.float64)
        gv = np.matmul(B, (sw * r)[..., None])[..., 0].astype(np.float64)
        Rb, tb = C[pb, :3, :3], C[pb, :3, 3]
        Ad = self.Ad
        Ad[:, :3, :3] = Rb
        Ad[:, 3:, 3:] = Rb
        _cross(tb[:, :, None], Rb, Ad[:, 3:, :3])  # [t]_x R, column by column
        ne.add_opposed(pa, pb, np.matmul(np.matmul(Ad, A), Ad.transpose(0, 2, 1)), np.matmul(Ad, gv[..., None])[..., 0])


def _pad_edges(edges: Sequence[FeatureEdge]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Feature edges as node ids (E,) x 2, homogeneous matches (E, 4, M) x 2, zero-padded, and their mask (E, M)."""
    M = max(1, max(len(e.p_i) for e in edges))
    E = len(edges)
    pi, pj = np.zeros((E, 4, M)), np.zeros((E, 4, M))
    pi[:, 3] = pj[:, 3] = 1.0
    mask = np.zeros((E, M), dtype=bool)
    for k, e in enumerate(edges):
        a = np.asarray(e.p_i, dtype=np.float64).reshape(-1, 3)
        b = np.asarray(e.p_j, dtype=np.float64).reshape(-1, 3)
        if len(a) != len(b):
            raise ValueError(f"edge ({e.i}, {e.j}): p_i and p_j differ in length")
        ok = np.isfinite(a).all(1) & np.isfinite(b).all(1)
        pi[k, :3, : len(a)] = np.where(ok[:, None], a, 0.0).T
        pj[k, :3, : len(b)] = np.where(ok[:, None], b, 0.0).T
        mask[k, : len(a)] = ok
    ia = np.array([e.i for e in edges], dtype=int)
    ib = np.array([e.j for e in edges], dtype=int)
    return ia, ib, pi, pj, mask


def _hat_rows(y: np.ndarray, sign: float) -> np.ndarray:
    """Rows of sign * [y]_x for component-major y (E, 3, M), stacked as (E, 3, 3, M): [row k, column c, match]."""
    z = np.zeros_like(y[:, 0])
    y0, y1, y2 = sign * y[:, 0], sign * y[:, 1], sign * y[:, 2]
    return np.stack([np.stack([z, -y2, y1], 1), np.stack([y2, z, -y0], 1), np.stack([-y1, y0, z], 1)], 1)


def _null_space_prior(H: np.ndarray, cfg: GraphConfig) -> tuple[np.ndarray, np.ndarray]:
    """Information matrix of the motion prior: weight ``cfg.w_m`` along the directions the data's 6x6 block ``H``
    leaves (nearly) free, eigenvalue below ``cfg.prior_null`` of the largest, and nothing along the others; and the
    directions below ``cfg.unmeasured_ratio`` of the largest, unit columns (6, k) of D delta (`Unmeasured`).
    Rotations are compared with translations as the displacement of a point ``cfg.prior_lever`` away (D)."""
    D = np.array([1.0, 1.0, 1.0] + [cfg.prior_lever] * 3)
    lam, V = np.linalg.eigh(H / np.outer(D, D))
    rel = lam / max(float(lam[-1]), 1e-12)
    weak = V[:, rel <= cfg.prior_null]
    return cfg.w_m * (weak @ weak.T) * np.outer(D, D), V[:, rel <= cfg.unmeasured_ratio]


@dataclass(frozen=True)
class Unmeasured:
    """A direction of a node's pose that the frame's data left free (information below ``graph.unmeasured_ratio``
    of the best-measured direction's), held by the motion prior: a ``kind`` "turn" about ``axis`` or "slide" along
    it (unit vector, object frame). The turn about a round shaft
    (a rotation about the shaft's direction, with the translation that keeps its axis line in place) is a turn; a
    direction whose rotation moves a point ``prior_lever`` away by under a tenth of its length is a slide."""

    kind: str
    axis: np.ndarray

    @classmethod
    def of(cls, free: np.ndarray) -> list[Unmeasured]:
        """The directions of `_null_space_prior`'s columns ``free``."""
        out = []
        for v in free.T:
            turn = np.linalg.norm(v[3:]) >= 0.1
            part = v[3:] if turn else v[:3]
            out.append(cls("turn" if turn else "slide", part / np.linalg.norm(part)))
        return out


def default_pairs(n: int, edges: Sequence[FeatureEdge]) -> list[tuple[int, int]]:
    """Directed node pairs for L_2D: both directions of every pair sharing a feature edge, or all i != j if none."""
    if not edges:
        return [(i, j) for i in range(n) for j in range(n) if i != j]
    out: set[tuple[int, int]] = set()
    for e in edges:
        if e.i != e.j:
            out.update({(e.i, e.j), (e.j, e.i)})
    return sorted(out)


def optimize_graph(
    nodes: list[GraphNode],
    edges: list[FeatureEdge],
    cfg: GraphConfig,
    sdf: SDFFn | None = None,
    sdf_nodes: Sequence[int] = (),
    pairs_2d: Sequence[tuple[int, int]] | None = None,
    priors: Sequence[tuple[int, np.ndarray]] = (),
    free_space: tuple[int, FreeSpace] | None = None,
    coverage: tuple[int, Coverage] | None = None,
    unmeasured: dict[int, list[Unmeasured]] | None = None,
) -> list[np.ndarray]:
    """Optimised 4x4 object-to-camera poses of ``nodes`` minimising the energy of eq. 8; fixed nodes are returned
    unchanged.

    - L_3D (eq. 9): rho(||pose_i^-1 p_i - pose_j^-1 p_j||) over every edge's matches, weight ``cfg.w_f``.
    - L_2D (eq. 10): for each directed pair (i, j) in ``pairs_2d`` (default `default_pairs`), node i's valid grid
      points p (at most ``cfg.max_assoc_points``) are mapped into camera j by T_ij = pose_j pose_i^-1, projected with
      K_j and associated with node j's point x_j at that pixel, gated by ``cfg.assoc_dist`` and
      ``cfg.assoc_normal_deg``; residual n_i(p) . (T_ij^-1 x_j - p), weight ``cfg.w_p``. Associations are recomputed
      every iteration.
    - L_SDF (eq. 11): with ``sdf`` given, ``sdf(points_obj (N, 3)) -> (psi (N,), grad (N, 3))`` is evaluated at
      pose_t^-1 p for the points p of every node t in ``sdf_nodes``; residual psi, weight ``cfg.w_s``.
    - Motion prior (not in the paper): for each ``(t, pose)`` in ``priors``, the residual log(C_t pose) (translation,
      and rotation times ``cfg.prior_lever``) with weight ``cfg.w_m``, worth that many point residuals, along the
      directions the data leave free only (`_null_space_prior`): a roll about a round shaft or a slide along it
      stays at ``pose`` instead of wandering, and the data alone decide every other direction. With ``unmeasured``
      given, ``unmeasured[t]`` is set to those directions at the last step (`Unmeasured`, also when w_m is 0).
    - Free space (not in the paper): with ``free_space`` = (t, fs), `FreeSpace.residuals` at node t, weight
      ``cfg.w_fs``: the model may not stand where the frame saw the background (a slide along a shaft moves its end
      out of the mask).
    - Coverage (not in the paper): with ``coverage`` = (t, cv), `Coverage.residuals` at node t, weight ``cfg.w_cv``:
      the frame's points may not stand where a keyframe saw the background (a slide along a shaft moves the end
      the frame shows beyond the end the keyframe saw). With L_FS it holds a slide from both sides.

    Every residual goes through the Huber loss with ``cfg.huber_delta``; ``cfg.iterations`` re-weighted Gauss-Newton
    steps are taken (parametrisation in the module docstring). Without a fixed node the gauge is held only by the
    damping, so the tracker should fix one node.
    """
    n = len(nodes)
    poses = [np.asarray(nd.pose, dtype=np.float64).copy() for nd in nodes]
    free = np.array([not nd.fixed for nd in nodes], dtype=bool)
    if n == 0 or not free.any():
        return poses
    C = _inv_batch(np.stack(poses))
    hd = float(cfg.huber_delta)

    pairs = default_pairs(n, edges) if pairs_2d is None else list(pairs_2d)
    pairs = [(i, j) for i, j in pairs if i != j and (free[i] or free[j])]
    edges = [e for e in edges if e.i != e.j and (free[e.i] or free[e.j]) and len(e.p_i) > 0]
    use_3d = bool(edges) and cfg.w_f > 0
    if use_3d:
        ea, eb, epi, epj, emask = _pad_edges(edges)
        eye = np.zeros((len(edges), 3, 3, emask.shape[1]))
        for k in range(3):
            eye[:, k, k] = 1.0
    use_2d = bool(pairs) and cfg.w_p > 0
    sdf_ids = np.array(sorted({int(s) for s in sdf_nodes if free[int(s)]}), dtype=int)
    use_sdf = sdf is not None and len(sdf_ids) > 0 and cfg.w_s > 0

    if use_2d or use_sdf:
        nd_data = _NodeData(nodes, cfg.max_assoc_points)
        ph, pmask = nd_data.ph, nd_data.mask
    if use_2d:
        proj = _Projective(nd_data, nodes, pairs, cfg)
    one_node_terms = []  # L_FS, then L_CV: (node, term, weight), each on one node's pose
    for pair, w in ((free_space, cfg.w_fs), (coverage, cfg.w_cv)):
        if pair is not None and w > 0 and free[pair[0]]:
            one_node_terms.append((*pair, w))

    free_at: dict[int, np.ndarray] = {}  # per prior node, the directions its data left free at the latest step
    for _ in range(cfg.iterations):
        ne = _Normal(n)

        if use_3d:
            # eq. 9: r = C_i p_i - C_j p_j; d r / d delta_i = [I, -[y_i]_x], d r / d delta_j = -[I, -[y_j]_x].
            ya = np.matmul(C[ea, :3, :], epi)
            yb = np.matmul(C[eb, :3, :], epj)
            r3 = ya - yb
            w = cfg.w_f * huber_weight(np.sqrt((r3 * r3).sum(1)), hd) * emask
            E, M = w.shape
            Ja = np.concatenate([eye, _hat_rows(ya, -1.0)], axis=2).transpose(0, 2, 1, 3).reshape(E, 6, 3 * M)
            Jb = np.concatenate([-eye, _hat_rows(yb, 1.0)], axis=2).transpose(0, 2, 1, 3).reshape(E, 6, 3 * M)
            ne.add(ea, Ja, r3.reshape(E, 3 * M), np.tile(w, (1, 3)), eb, Jb)

        if use_2d:
            proj.add_to(ne, C)

        if use_sdf:
            # eq. 11: r = psi(C_t p); d r / d delta_t = [grad, y x grad].
            ys, ms = np.matmul(C[sdf_ids, :3, :], ph[sdf_ids]), pmask[sdf_ids]
            psi, grad = sdf(ys.transpose(0, 2, 1)[ms])
            r = np.zeros(ms.shape)
            gr = np.zeros(ms.shape + (3,))
            r[ms] = np.asarray(psi, dtype=np.float64).reshape(-1)
            gr[ms] = np.asarray(grad, dtype=np.float64).reshape(-1, 3)
            good = ms & np.isfinite(r) & np.isfinite(gr).all(-1)
            r = np.where(good, r, 0.0)
            gr = np.where(good[..., None], gr, 0.0).transpose(0, 2, 1)
            Js = np.empty((len(sdf_ids), 6, ms.shape[1]))
            Js[:, :3] = gr
            _cross(ys, gr, Js[:, 3:])
            ne.add(sdf_ids, Js, r, cfg.w_s * huber_weight(r, hd) * good)

        for t, term, w in one_node_terms:
            r, J = term.residuals(C[t], cfg)
            ne.add(np.array([t]), J[None], r[None], (w * huber_weight(r, hd))[None])

        for t, prior in priors:
            if free[t] and (cfg.w_m > 0 or unmeasured is not None):
                E = C[t] @ prior  # C_t times the prior's pose: identity at the prior
                W, free_at[t] = _null_space_prior(ne.H[t, t], cfg)
                ne.H[t, t] += W
                ne.g[t] += W @ np.concatenate([E[:3, 3], so3_log(E[:3, :3])])

        step = ne.solve(free, cfg.damping)
        if not np.all(np.isfinite(step)):
            break
        for k in np.flatnonzero(free):
            C[k] = se3_exp(step[k]) @ C[k]
        if np.abs(step).max() < 1e-10:
            break

    if unmeasured is not None:
        unmeasured.update({t: Unmeasured.of(v) for t, v in free_at.items()})
    return [poses[k] if not free[k] else inv_T(C[k]) for k in range(n)]
