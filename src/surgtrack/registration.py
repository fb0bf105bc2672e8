"""Stage 1, CAD-free registration: the Instrument SDF Psi fitted to posed, masked keyframe depth (paper eqs. 1-3).

Psi lives on a dense voxel grid in the object frame (trilinear interpolation), starts from a TSDF fusion of the
keyframes (`surgtrack.tsdf`) and is refined by Adam on

    L = alpha L_occ + beta L_surf + w_free L_free + w_eik L_eik

- L_surf (eq. 3): mean over V_surf of (Psi(v) + d_v - d_Delta)^2, V_surf the samples of instrument rays in the band
  [d_Delta - truncation, d_Delta + surf_behind] around the observed depth d_Delta, d_v the sample's depth (camera z).
  The depth gap d_v - d_Delta is projected on the observed surface normal (times the incidence cosine of the depth
  map), so that Psi regresses a distance rather than a projective distance that grazing rays overestimate.
- L_occ (eq. 2): mean over V_occ of (Psi(v) - delta)^2, V_occ the samples behind an occluder (a non-instrument
  pixel's observed depth) or on rays of invalid depth on/next to the instrument mask, that lie in the near-surface
  exterior of the current field (0 <= Psi < truncation): there the field is held at a small positive value instead
  of being carved to empty; samples the field already places inside are left to the other views.
- L_free: mean of relu(tau - Psi)^2 over samples a ray traversed in front of its observed surface: tau = truncation
  in front of an instrument surface (normal-projected gap, capped), tau = delta on rays that miss the instrument
  (they may graze it). Rays of occluders give free space only in front of the occluder.
- L_eik: mean of (|grad Psi| - 1)^2 over grid nodes with |Psi| < 2 truncation (central differences).

With ``cfg.refine_poses`` the keyframe poses are refined jointly with Psi, as BundleSDF does: each view but the
first gets a rigid correction D_i of the object frame (rotation vector and translation, each component bounded by
tanh to ``refine_rot_deg`` / ``refine_trans``), applied to its rays' samples, and Adam minimises L over Psi and the
D_i together. The refined pose is xi_i D_i^-1.

Sign convention: Psi > 0 outside the instrument (towards the camera), Psi < 0 inside, metres: on a ray
Psi(v) ~ d_Delta - d_v. Residuals and losses are computed in units of the truncation (the grid stores Psi / truncation).

With ``cfg.occ_surf = False`` (the paper's "w/o occlusion and texture optimisation" ablation) there is no L_occ: the
fit is a plain TSDF regression integrated along the rays, and every non-instrument ray is free space along its whole
length, so occluders carve the shape as in a naive system.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import threading
import time
import weakref
from dataclasses import asdict, replace
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from scipy.spatial import cKDTree
from skimage import measure

from .config import SDFConfig
from .geometry import depth_to_xyz, inv_T, is_rotation, make_T
from .tsdf import EMPTY, HOLE, SEEN, SURF, Grid, View, classify_pixels, fuse_tsdf, pick_device

__all__ = ["BackgroundFitter", "InstrumentSDF", "View"]


class _Rays:
    """Rays of a set of views that cross the grid box, on the fitting device."""

    def __init__(self, surf: dict[str, torch.Tensor], other: dict[str, torch.Tensor]):
        self.surf = surf  # o, d (direction with unit camera z), depth, znear, cos, view (index)
        self.other = other  # o, d, depth (0 invalid), znear, zfar, code, view


class _PoseCorrections:
    """Bounded rigid corrections D_i of the views (grid frame), view 0 fixed: x -> R_i x + t_i."""

    def __init__(self, n: int, cfg: SDFConfig, device: torch.device):
        self.xi = torch.zeros((n, 6), device=device, requires_grad=True)
        self.free = torch.ones((n, 1), device=device)
        self.free[0] = 0.0
        self.bound = torch.tensor([np.radians(cfg.refine_rot_deg)] * 3 + [cfg.refine_trans] * 3, device=device,
                                  dtype=torch.float32)

    def rt(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotations (n, 3, 3) and translations (n, 3)."""
        v = torch.tanh(self.xi) * self.bound * self.free
        w = v[:, :3]
        zero = torch.zeros_like(w[:, 0])
        skew = torch.stack([zero, -w[:, 2], w[:, 1], w[:, 2], zero, -w[:, 0], -w[:, 1], w[:, 0], zero], dim=1)
        return torch.linalg.matrix_exp(skew.view(-1, 3, 3)), v[:, 3:]

    def move(self, p: torch.Tensor, view: torch.Tensor, rt: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
        """Samples p (N, S, 3) of rays from views `view` (N,), corrected."""
        R, t = rt[0][view], rt[1][view]
        return torch.einsum("nij,nsj->nsi", R, p) + t[:, None]


def _box_interval(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ray parameter of rays o + t d through the box [lo, hi]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
    t1 = np.nan_to_num(t1, nan=-np.inf)
    t2 = np.nan_to_num(t2, nan=np.inf)
    return np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)


def _incidence_cos(view: View, floor: float = 0.2) -> np.ndarray:
    """|cos| of the angle between each pixel's viewing ray and the surface normal of the depth map (H, W).

    Pixels without a normal (a neighbour missing or across the mask border) get 1; the value is floored at `floor`.
    """
    xyz = depth_to_xyz(view.depth, view.K)
    ok = (view.depth > 0) & view.mask.astype(bool)
    cos = np.ones(view.depth.shape)
    dx = xyz[1:-1, 2:] - xyz[1:-1, :-2]
    dy = xyz[2:, 1:-1] - xyz[:-2, 1:-1]
    n = np.cross(dx, dy)
    r = xyz[1:-1, 1:-1]
    good = ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1] & ok[1:-1, 1:-1]
    num = np.abs(np.einsum("ijk,ijk->ij", n, r))
    den = np.linalg.norm(n, axis=-1) * np.linalg.norm(r, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(good & (den > 0), num / den, 1.0)
    cos[1:-1, 1:-1] = np.clip(c, floor, 1.0)
    return cos


_SURF_KEYS = ("o", "d", "depth", "znear", "cos")
_OTHER_KEYS = ("o", "d", "depth", "znear", "zfar", "code")
ViewRays = tuple[dict[str, np.ndarray], dict[str, np.ndarray]]


def _rays_of(view: View, grid: Grid, cfg: SDFConfig) -> ViewRays:
    """One view's rays that cross the grid box (grid frame): instrument rays (V_surf) and the others."""
    lo, hi = grid.origin, grid.upper
    h, w = view.depth.shape
    codes = classify_pixels(view, cfg.occ_dilate)
    if not cfg.occ_surf:
        off_hole = (codes == HOLE) & ~view.mask.astype(bool)
        codes = np.where(off_hole, EMPTY, codes).astype(np.int8)
        codes[(codes == HOLE)] = -1  # invalid depth on the mask: no evidence without occlusion handling
    keep = codes >= 0
    if cfg.ray_stride > 1:
        grid_px = np.zeros((h, w), dtype=bool)
        grid_px[:: cfg.ray_stride, :: cfg.ray_stride] = True
        keep &= grid_px | (codes == SURF)
    v, u = np.nonzero(keep)
    code = codes[v, u]
    cos_map = _incidence_cos(view)
    depth = view.depth[v, u].astype(np.float64)
    Kinv = np.linalg.inv(view.K)
    cam = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64) @ Kinv.T
    cam /= cam[:, 2:3]
    T_co = inv_T(view.pose)
    d = cam @ T_co[:3, :3].T
    o = np.broadcast_to(T_co[:3, 3], d.shape)
    t0, t1 = _box_interval(o, d, lo, hi)
    t0 = np.maximum(t0, 1e-3)
    is_surf = code == SURF
    s = is_surf & (depth + cfg.truncation > t0) & (depth - cfg.truncation < t1)
    r = ~is_surf & (t1 > t0)
    cos = cos_map[v, u]
    surf = zip(_SURF_KEYS, (o[s], d[s], depth[s], t0[s], cos[s]), strict=True)
    other = zip(_OTHER_KEYS, (o[r], d[r], depth[r], t0[r], t1[r], code[r]), strict=True)
    def as_read(part: zip) -> dict[str, np.ndarray]:
        """In the types the fit reads (float32): a kept view costs about 1 MB at 640x480."""
        return {key: val.astype(np.int8 if key == "code" else np.float32) for key, val in part}

    return as_read(surf), as_read(other)


def _gather_rays(per_view: list[ViewRays], device: torch.device) -> _Rays:
    """The views' rays in one batch on the fitting device, each with its view's index."""

    def cat(parts: list[dict[str, np.ndarray]], keys: tuple[str, ...]) -> dict[str, torch.Tensor]:
        out = {}
        for key in (*keys, "view"):
            vals = [np.full(len(p["depth"]), i) if key == "view" else p[key] for i, p in enumerate(parts)]
            arr = np.concatenate(vals) if vals else np.zeros((0, 3) if key in ("o", "d") else (0,))
            dtype = torch.long if key in ("code", "view") else torch.float32
            out[key] = torch.as_tensor(np.ascontiguousarray(arr), device=device, dtype=dtype)
        return out

    return _Rays(cat([p[0] for p in per_view], _SURF_KEYS), cat([p[1] for p in per_view], _OTHER_KEYS))


def _plateaued(losses: list[float], tol: float) -> bool:
    """True when the mean loss of the last quarter of the steps is within `tol` (relative) of the quarter before."""
    q = len(losses) // 4
    if q < 5:
        return False
    last, prev = float(np.mean(losses[-q:])), float(np.mean(losses[-2 * q : -q]))
    return bool(prev > 0 and (prev - last) / prev < tol)


class InstrumentSDF:
    """Dense-grid signed distance field Psi of the instrument in the object frame (paper eq. 1).

    `center` (object frame) and `extent` (side length, scalar or per axis, metres) set the box the grid covers; the
    voxel is `cfg.voxel_size`. `rotation` R (3x3, default identity) orients the box: its axes are the rows of R, so
    a lattice node g in the grid frame is the object-frame point R^T g. A box along an elongated instrument holds
    far fewer voxels than an axis-aligned one around it. The grid runs on CUDA when torch sees one unless `device`
    says otherwise.
    """

    def __init__(
        self, cfg: SDFConfig, center: np.ndarray, extent: float | np.ndarray, device: str | torch.device | None = None,
        rotation: np.ndarray | None = None,
    ):
        self.cfg = cfg
        self.device = pick_device(device)
        self.rotation = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        if not is_rotation(self.rotation):
            raise ValueError("InstrumentSDF rotation is not a rotation matrix")
        self.grid = Grid.around(self.rotation @ np.asarray(center, dtype=np.float64), extent, cfg.voxel_size)
        self.psi = torch.ones(self.grid.shape, device=self.device)  # Psi / truncation
        self.weight = torch.zeros(self.grid.shape, device=self.device)
        self.fitted = False
        self.converged = False
        self.last_losses: dict[str, float] = {}
        self.refined_poses: dict[str, np.ndarray] = {}  # view id -> jointly refined pose (cfg.refine_poses)
        self._host: np.ndarray | None = None
        self._rays: dict[tuple, ViewRays] = {}  # `_view_rays`' cache

    # -- fitting -----------------------------------------------------------------------------------------------
    def _object_from_grid(self) -> np.ndarray:
        """4x4 T with x_obj = T x_grid."""
        return make_T(self.rotation.T, np.zeros(3))

    def _in_grid(self, views: list[View]) -> list[View]:
        """The views posed in the grid frame (x_cam = pose @ T x_grid, T = `_object_from_grid`)."""
        T = self._object_from_grid()
        return [replace(v, pose=v.pose @ T) for v in views]

    def init_tsdf(self, views: list[View]) -> None:
        """Initialise Psi by TSDF fusion of the views (occlusion-aware unless cfg.occ_surf is False)."""
        c = self.cfg
        self.psi, self.weight = fuse_tsdf(self._in_grid(views), self.grid, c.truncation, c.occ_surf, c.occ_dilate,
                                          self.device)
        self._host = None

    def _view_rays(self, views: list[View]) -> list[ViewRays]:
        """Each view's rays in the grid frame. A view with an id is gathered once per pose and box: its rays are
        kept until a fit without it (a refit mostly sees the keyframes of the last one, and gathering them costs
        about a third of a 60-step refit)."""
        kept, out = {}, []
        for view in self._in_grid(views):
            key = (view.id, view.pose.tobytes(), self.grid.origin.tobytes(), self.grid.shape)
            rays = self._rays.get(key) if view.id else None
            out.append(rays if rays is not None else _rays_of(view, self.grid, self.cfg))
            if view.id:
                kept[key] = out[-1]
        self._rays = kept
        return out

    def forget_rays(self) -> None:
        """Drop the rays `_view_rays` keeps between fits (about 1 MB a view at 640x480): the next fit gathers every
        view anew."""
        self._rays = {}

    def refit(self, views: list[View], iterations: int | None = None, rounds: int = 0) -> dict:
        """Incremental refit: warm start from the current field, TSDF values only where nothing was observed yet,
        then ``iterations`` Adam steps (None: ``cfg.iterations``). The first fit of an unfitted field (TSDF start)
        always runs ``cfg.iterations``: a short one is far from a plateau, and an unconverged field stays out of the
        posture graph. While the field has not converged, up to ``rounds`` more fits of ``iterations`` steps follow
        on the same views (the report merges them)."""
        if not self.fitted:
            self.init_tsdf(views)
            iterations = None
        else:
            c = self.cfg
            psi, weight = fuse_tsdf(self._in_grid(views), self.grid, c.truncation, c.occ_surf, c.occ_dilate,
                                    self.device)
            new = (self.weight == 0) & (weight > 0)
            self.psi = torch.where(new, psi, self.psi)
            self.weight = torch.maximum(self.weight, weight)
        report = self.fit(views, iterations)
        for _ in range(rounds):
            if self.converged:
                break
            more = self.fit(views, iterations)
            more["history"] = {k: report["history"][k] + v for k, v in more["history"].items()}
            more["seconds"] += report["seconds"]
            report = more
        return report

    def _sample(self, vol: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Trilinear Psi / truncation at object-frame points (N, 3) and a mask of points inside the grid."""
        lo = torch.as_tensor(self.grid.origin, device=p.device, dtype=torch.float32)
        span = torch.as_tensor(self.grid.upper - self.grid.origin, device=p.device, dtype=torch.float32)
        g = 2.0 * (p - lo) / span - 1.0
        inside = (g.abs() <= 1.0).all(dim=1)
        val = F.grid_sample(vol, g.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="border", align_corners=True)
        return val.view(-1), inside

    def _losses(self, param: torch.Tensor, rays: _Rays, gen: torch.Generator,
                corr: _PoseCorrections | None = None) -> dict[str, torch.Tensor]:
        c = self.cfg
        dev = param.device
        rt = corr.rt() if corr is not None else None

        def place(o: torch.Tensor, d: torch.Tensor, z: torch.Tensor, view: torch.Tensor) -> torch.Tensor:
            """Sample points (N * S, 3) at ray parameters z (N, S), moved by the views' corrections."""
            p = o[:, None] + z[..., None] * d[:, None]
            return (p if corr is None else corr.move(p, view, rt)).reshape(-1, 3)

        vol = param.permute(2, 1, 0)[None, None]  # (1, 1, nz, ny, nx): grid_sample reads (x, y, z)
        tr = c.truncation
        S = c.samples_per_ray
        zero = torch.zeros((), device=dev)
        out = {"surf": zero, "free": zero, "occ": zero}

        sr = rays.surf
        if sr["depth"].numel():
            idx = torch.randint(sr["depth"].numel(), (c.batch_rays,), generator=gen, device=dev)
            o, d, dep, zn, cs = sr["o"][idx], sr["d"][idx], sr["depth"][idx], sr["znear"][idx], sr["cos"][idx]
            vi = sr["view"][idx]
            k = torch.arange(S, device=dev, dtype=torch.float32)
            jit = torch.rand((idx.numel(), S), generator=gen, device=dev)
            behind = min(c.surf_behind, tr)
            zb = dep[:, None] - tr + (tr + behind) * (k + jit) / S
            val, inside = self._sample(vol, place(o, d, zb, vi))
            res = val + (zb.reshape(-1) - dep.repeat_interleave(S)) * cs.repeat_interleave(S) / tr
            m = inside & (zb.reshape(-1) > zn.repeat_interleave(S))
            surf_res = res[m]
            surf_len = torch.full_like(surf_res, (tr + behind) / S)
            nf = max(S // 2, 1)
            span = (dep - tr - zn).clamp(min=0.0)
            jit = torch.rand((idx.numel(), nf), generator=gen, device=dev)
            zf = zn[:, None] + span[:, None] * (torch.arange(nf, device=dev) + jit) / nf
            fval, finside = self._sample(vol, place(o, d, zf, vi))
            fm = finside & (span > 0).repeat_interleave(nf)
            # In front of an instrument surface the distance to it is at least the normal-projected depth gap.
            ftarget = ((dep[:, None] - zf) * cs[:, None] / tr).clamp(max=1.0).reshape(-1)
            free_parts = [fval[fm] - ftarget[fm] + 1.0]
            free_lens = [(span / nf).repeat_interleave(nf)[fm]]
        else:
            surf_res = surf_len = torch.zeros(0, device=dev)
            free_parts, free_lens = [], []

        orr = rays.other
        occ_parts: list[torch.Tensor] = []
        if orr["depth"].numel():
            idx = torch.randint(orr["depth"].numel(), (c.batch_rays,), generator=gen, device=dev)
            o, d, dep = orr["o"][idx], orr["d"][idx], orr["depth"][idx]
            zn, zf, code, vi = orr["znear"][idx], orr["zfar"][idx], orr["code"][idx], orr["view"][idx]
            jit = torch.rand((idx.numel(), S), generator=gen, device=dev)
            z = zn[:, None] + (zf - zn)[:, None] * (torch.arange(S, device=dev) + jit) / S
            val, inside = self._sample(vol, place(o, d, z, vi))
            z = z.reshape(-1)
            dep = dep.repeat_interleave(S)
            code = code.repeat_interleave(S)
            seen = code == SEEN
            if c.occ_surf:
                free = (code == EMPTY) | (seen & (z < dep - tr))
                occ = (code == HOLE) | (seen & (z > dep))
                v_det = val.detach()
                occ = occ & inside & (v_det >= 0) & (v_det < 1)
                if occ.any():
                    occ_parts.append(val[occ] - c.delta / tr)
            else:
                free = (code == EMPTY) | seen
            # A ray that misses the instrument may graze it: it only says Psi >= delta along its free part.
            free_parts.append(val[free & inside] + (1.0 - c.delta / tr if c.occ_surf else 0.0))
            free_lens.append(((zf - zn) / S).repeat_interleave(S)[free & inside])
        free_val = torch.cat(free_parts) if free_parts else torch.zeros(0, device=dev)
        if c.occ_surf:
            if surf_res.numel():
                out["surf"] = (surf_res**2).mean()
            if free_val.numel():
                out["free"] = (torch.relu(1.0 - free_val) ** 2).mean()
            if occ_parts:
                out["occ"] = (torch.cat(occ_parts) ** 2).mean()
        else:
            # Plain TSDF regression, integrated along the rays (each sample weighted by the ray length it stands
            # for, as TSDF fusion votes per voxel): free space has target +truncation.
            res = torch.cat([surf_res, free_val - 1.0])
            lens = torch.cat([surf_len, *free_lens])
            if res.numel():
                out["surf"] = (lens * res**2).sum() / lens.sum()

        # Eikonal term on random interior voxels (a grid-wide pass would cost more than all the rays).
        n = 4 * c.batch_rays
        i, j, k = (torch.randint(1, size - 1, (n,), generator=gen, device=dev) for size in param.shape)
        gx = (param[i + 1, j, k] - param[i - 1, j, k]) / 2
        gy = (param[i, j + 1, k] - param[i, j - 1, k]) / 2
        gz = (param[i, j, k + 1] - param[i, j, k - 1]) / 2
        gnorm = torch.sqrt(gx**2 + gy**2 + gz**2 + 1e-12) * tr / self.grid.voxel
        band = param[i, j, k].detach().abs() < 2.0
        out["eik"] = ((gnorm[band] - 1.0) ** 2).mean() if band.any() else zero
        out["total"] = c.alpha * out["occ"] + c.beta * out["surf"] + c.w_free * out["free"] + c.w_eik * out["eik"]
        return out

    def fit(self, views: list[View], iterations: int | None = None, seed: int = 0) -> dict:
        """Adam on the grid values with L = alpha L_occ (eq. 2) + beta L_surf (eq. 3) + w_free L_free + w_eik L_eik.

        Starts from the current field (call `init_tsdf` first for a fresh fit). Returns the loss history (every
        step, dimensionless: residuals in units of the truncation), the final losses, `surf_rms_m` and `seconds`;
        with ``cfg.refine_poses`` also `poses`, the views' jointly refined poses (object-to-camera; the first view's
        unchanged), which `refined_poses` keeps by view id.
        """
        t0 = time.perf_counter()
        n_iter = self.cfg.iterations if iterations is None else int(iterations)
        rays = _gather_rays(self._view_rays(views), self.device)
        gen = torch.Generator(device=self.device)
        gen.manual_seed(seed)
        param = self.psi.detach().clone().requires_grad_(True)
        opt = torch.optim.Adam([param], lr=self.cfg.lr)
        corr = _PoseCorrections(len(views), self.cfg, self.device) if self.cfg.refine_poses and views else None
        pose_opt = torch.optim.Adam([corr.xi], lr=self.cfg.refine_lr) if corr is not None else None
        history: dict[str, list[float]] = {k: [] for k in ("total", "surf", "occ", "free", "eik")}
        for _ in range(n_iter):
            opt.zero_grad(set_to_none=True)
            if pose_opt is not None:
                pose_opt.zero_grad(set_to_none=True)
            losses = self._losses(param, rays, gen, corr)
            losses["total"].backward()
            opt.step()
            if pose_opt is not None:
                pose_opt.step()
            for k in history:
                history[k].append(float(losses[k].detach()))
        self.psi = param.detach()
        self._host = None
        self.fitted = True
        poses = self._refined(views, corr) if corr is not None else None
        if poses is not None:
            self.refined_poses = {v.id: T for v, T in zip(views, poses, strict=True)}
        tail = max(1, n_iter // 10)
        final = {k: float(np.mean(v[-tail:])) if v else float("nan") for k, v in history.items()}
        surf_rms = float(np.sqrt(final["surf"])) * self.cfg.truncation if n_iter else float("nan")
        self.converged = self.converged or _plateaued(history["total"], self.cfg.converged_tol)
        self.last_losses = final
        return {
            "history": history,
            "final": final,
            "surf_rms_m": surf_rms,
            "seconds": time.perf_counter() - t0,
            "rays": (int(rays.surf["depth"].numel()), int(rays.other["depth"].numel())),
            **({"poses": poses} if poses is not None else {}),
        }

    def _refined(self, views: list[View], corr: _PoseCorrections) -> list[np.ndarray]:
        """Object-to-camera poses xi_i T D_i^-1 T^-1 of the views after the fit (D_i acts in the grid frame, T the
        object-from-grid rotation)."""
        with torch.no_grad():
            R, t = (x.double().cpu().numpy() for x in corr.rt())
        T = self._object_from_grid()
        return [view.pose @ T @ inv_T(make_T(Ri, ti)) @ inv_T(T) for view, Ri, ti in zip(views, R, t, strict=True)]

    # -- queries -----------------------------------------------------------------------------------------------
    def __call__(self, points_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`query` within the grid box, NaN beyond it (the posture graph's L_SDF hook, eq. 11): the field knows
        nothing of the space outside its box, and a point of a shaft seen beyond it would pull the pose along the
        shaft towards the box."""
        psi, grad = self.query(points_obj)
        p = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3) @ self.rotation.T
        outside = ((p < self.grid.origin) | (p > self.grid.upper)).any(axis=1)
        psi[outside] = np.nan
        grad[outside] = np.nan
        return psi, grad

    def values(self) -> np.ndarray:
        """Psi on the grid nodes, (nx, ny, nz) float32 metres (a cached host copy)."""
        if self._host is None:
            self._host = (self.psi.detach() * self.cfg.truncation).float().cpu().numpy()
        return self._host

    def query(self, points_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Psi (N,) and its gradient (N, 3) at object-frame points (N, 3), metres; numpy trilinear on a host copy.

        Outside the grid box Psi is the value at the nearest box point plus the distance to the box.
        """
        vol = self.values()
        p = np.asarray(points_obj, dtype=np.float64).reshape(-1, 3) @ self.rotation.T  # grid frame
        n = np.array(self.grid.shape)
        lo, hi = self.grid.origin, self.grid.upper
        pc = np.clip(p, lo, hi)
        g = (pc - lo) / self.grid.voxel
        i0 = np.minimum(np.floor(g).astype(np.int64), n - 2)
        f = g - i0
        flat = vol.reshape(-1)
        ny, nz = int(n[1]), int(n[2])
        base = (i0[:, 0] * ny + i0[:, 1]) * nz + i0[:, 2]
        c = {}
        for a in (0, 1):
            for b in (0, 1):
                for e in (0, 1):
                    c[a, b, e] = flat[base + (a * ny + b) * nz + e].astype(np.float64)
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        c00 = c[0, 0, 0] * (1 - fz) + c[0, 0, 1] * fz
        c01 = c[0, 1, 0] * (1 - fz) + c[0, 1, 1] * fz
        c10 = c[1, 0, 0] * (1 - fz) + c[1, 0, 1] * fz
        c11 = c[1, 1, 0] * (1 - fz) + c[1, 1, 1] * fz
        c0 = c00 * (1 - fy) + c01 * fy
        c1 = c10 * (1 - fy) + c11 * fy
        val = c0 * (1 - fx) + c1 * fx
        dx = c1 - c0
        dy = (c01 - c00) * (1 - fx) + (c11 - c10) * fx
        dz0 = (c[0, 0, 1] - c[0, 0, 0]) * (1 - fy) + (c[0, 1, 1] - c[0, 1, 0]) * fy
        dz1 = (c[1, 0, 1] - c[1, 0, 0]) * (1 - fy) + (c[1, 1, 1] - c[1, 1, 0]) * fy
        dz = dz0 * (1 - fx) + dz1 * fx
        grad = np.stack([dx, dy, dz], axis=1) / self.grid.voxel
        out = p - pc
        dist = np.linalg.norm(out, axis=1)
        far = dist > 0
        if far.any():
            val[far] += dist[far]
            grad[far] = out[far] / dist[far, None]
        return val, grad @ self.rotation

    def mesh(self, keep_frac: float = 0.1, seen: np.ndarray | None = None, seen_dist: float = 0.0) -> trimesh.Trimesh:
        """Zero level set by marching cubes (object frame, metres), outward normals. With `seen` points (object
        frame), only faces whose centroids lie within `seen_dist` of them are kept: the surfaces the field closes
        where nothing was seen (box walls, the far side) go. A connected component whose (seen) area is less than
        `keep_frac` of the largest's is dropped as a floater; its area counts only its seen faces, so a box wall
        does not outweigh a thin shaft the video shows."""
        vol = self.values()
        if not (vol.min() < 0 < vol.max()):
            return trimesh.Trimesh()
        v = self.grid.voxel
        verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=(v, v, v))
        m = trimesh.Trimesh((verts + self.grid.origin) @ self.rotation, faces, process=True)
        kept = np.ones(len(m.faces), dtype=bool)
        if seen is not None and len(seen):
            d, _ = cKDTree(seen).query(m.triangles_center, distance_upper_bound=seen_dist)
            kept = np.isfinite(d)
        labels = trimesh.graph.connected_component_labels(m.face_adjacency, node_count=len(m.faces))
        area = np.bincount(labels, weights=m.area_faces * kept)
        kept &= area[labels] >= keep_frac * area.max()
        if not kept.any():
            return trimesh.Trimesh()
        if not kept.all():
            part = m.submesh([np.nonzero(kept)[0]], append=True)
            m = part if isinstance(part, trimesh.Trimesh) else trimesh.Trimesh()
        if len(m.faces):
            # Normals point to increasing Psi (outwards).
            c = m.triangles_center
            _, gr = self.query(c)
            if np.sum(np.einsum("ij,ij->i", m.face_normals, gr)) < 0:
                m.invert()
        return m

    # -- persistence -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, np.ndarray]:
        """Plain numpy state (fits in an npz or a model file): grid, weights, lattice, config, flags."""
        return {
            "psi": self.values().copy(),
            "weight": self.weight.detach().cpu().numpy().astype(np.float32),
            "origin": self.grid.origin.copy(),
            "rotation": self.rotation.copy(),
            "voxel": np.float64(self.grid.voxel),
            "flags": np.array([self.fitted, self.converged]),
            "cfg": np.array(json.dumps(asdict(self.cfg))),
        }

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        """Restore a `state_dict`; the lattice (and its rotation, identity when absent) is taken from the state."""
        psi = np.asarray(state["psi"], dtype=np.float32)
        self.rotation = np.asarray(state.get("rotation", np.eye(3)), dtype=np.float64).reshape(3, 3)
        self.grid = Grid(
            origin=np.asarray(state["origin"], dtype=np.float64),
            voxel=float(state["voxel"]),
            shape=(int(psi.shape[0]), int(psi.shape[1]), int(psi.shape[2])),
        )
        self.psi = torch.as_tensor(psi / self.cfg.truncation, device=self.device)
        self.weight = torch.as_tensor(np.asarray(state["weight"], dtype=np.float32), device=self.device)
        self.fitted, self.converged = (bool(x) for x in np.asarray(state["flags"]))
        self._host = None

    @classmethod
    def from_state_dict(cls, state: dict[str, np.ndarray], device: str | torch.device | None = None) -> InstrumentSDF:
        cfg = SDFConfig(**json.loads(str(np.asarray(state["cfg"]))))
        sdf = cls(cfg, np.zeros(3), float(state["voxel"]), device=device)  # lattice and rotation from the state
        sdf.load_state_dict(state)
        return sdf

    def to_npz(self, path: str | Path) -> None:
        np.savez_compressed(path, **self.state_dict())

    @classmethod
    def from_npz(cls, path: str | Path, device: str | torch.device | None = None) -> InstrumentSDF:
        with np.load(path) as z:
            return cls.from_state_dict({k: z[k] for k in z.files}, device=device)

    def lengthened(self, lo: float, hi: float) -> InstrumentSDF:
        """A copy whose box also spans [lo, hi] (m, grid frame) along its first axis, in whole voxels: the field's
        values are kept and the added voxels start unobserved (the next `refit` fills them by TSDF fusion)."""
        v, n = self.grid.voxel, self.grid.shape[0]
        below = max(int(np.ceil((self.grid.origin[0] - lo) / v - 1e-6)), 0)
        above = max(int(np.ceil((hi - self.grid.upper[0]) / v - 1e-6)), 0)
        other = self.copy()
        other.grid = replace(self.grid, origin=self.grid.origin - [below * v, 0.0, 0.0],
                             shape=(n + below + above, *self.grid.shape[1:]))
        other.psi = F.pad(self.psi, (0, 0, 0, 0, below, above), value=1.0)
        other.weight = F.pad(self.weight, (0, 0, 0, 0, below, above), value=0.0)
        return other

    def copy(self) -> InstrumentSDF:
        """Independent copy (tensors cloned)."""
        other = copy.copy(self)
        other.psi = self.psi.detach().clone()
        other.weight = self.weight.detach().clone()
        other.last_losses = dict(self.last_losses)
        other.refined_poses = dict(self.refined_poses)
        other._host = None
        return other


class BackgroundFitter:
    """Refits the Instrument SDF in a process of its own (`sdf_worker`) as keyframes arrive; the tracker never
    waits on it.

    `submit(views)` hands the current keyframes over and returns at once; a request that arrives while a fit runs
    replaces any older queued one (only the newest keyframe set is fitted next). The first fit of an unfitted field
    runs its ``cfg.iterations``; each later refit warm-starts from the last completed field (`InstrumentSDF.refit`)
    for ``iterations`` steps (None: ``cfg.iterations`` too). Until the field converges, a fit goes on with the same
    views for up to ``cfg.converge_rounds`` more (an unconverged field stays out of the posture graph, and the
    views of each new request would move its plateau away). `latest()` returns the last completed field, or None,
    without taking a lock. The tracker must treat that object as read-only; every refit produces a new one.

    A thread of this process sends the requests and receives the fields; it waits on the pipe, so the fit itself
    never holds this process's interpreter lock (on a thread it held it for much of each step, and the posture
    graph waited). ``num_threads`` sets torch's thread count in the worker (1 leaves the other core of a 2-core
    machine to the tracker). On CUDA the worker's GPU does the work. The worker stops at `close`, when the fitter
    is dropped, or at interpreter exit.
    """

    def __init__(self, sdf: InstrumentSDF, iterations: int | None = None, num_threads: int | None = None):
        self._link = _WorkerLink((sdf.state_dict(), iterations, num_threads), sdf.device,
                                 sdf if sdf.fitted else None)
        self._stop_worker = weakref.finalize(self, self._link.shutdown)

    def submit(self, views: list[View]) -> None:
        """Queue a refit on these keyframes (non-blocking)."""
        link = self._link
        with link.cond:
            if link.stop:
                raise RuntimeError("BackgroundFitter is closed")
            if not link.dead:
                link.pending = list(views)
            link.cond.notify_all()

    def latest(self) -> InstrumentSDF | None:
        """The most recently completed field, or None; never waits."""
        return self._link.latest

    @property
    def busy(self) -> bool:
        return self._link.busy or self._link.pending is not None

    @property
    def error(self) -> BaseException | None:
        """The last fit's failure, or the worker's end when it died; None while all is well."""
        return self._link.error

    @property
    def fits_done(self) -> int:
        return self._link.fits_done

    @property
    def last_report(self) -> dict | None:
        """The last completed fit's report (`InstrumentSDF.fit`)."""
        return self._link.last_report

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every submitted request is fitted (for tools and tests, not the tracker); False on timeout."""
        link = self._link
        with link.cond:
            return link.cond.wait_for(lambda: not self.busy or link.stop or link.dead, timeout=timeout)

    def close(self, wait: bool = False) -> None:
        """Stop the worker: after the queued request when `wait`, else at once (a fit in progress is dropped)."""
        if wait:
            self.wait()
        self._stop_worker()


class _WorkerLink:
    """The worker process of a `BackgroundFitter` and what the fitter shares with the thread that talks to it. The
    thread holds this, not the fitter, so that a fitter dropped without `close` is collected and its worker
    stopped."""

    def __init__(self, start: tuple, device: torch.device, latest: InstrumentSDF | None):
        self.device = device
        self.latest = latest
        self.pending: list[View] | None = None
        self.busy = False
        self.stop = False  # closed, or the fitter dropped
        self.dead = False  # the worker is gone
        self.cond = threading.Condition()
        self.error: BaseException | None = None
        self.fits_done = 0
        self.last_report: dict | None = None
        worker_in, to_worker = os.pipe()  # (read end, write end)
        from_worker, worker_out = os.pipe()
        package_root = str(Path(__file__).resolve().parents[1])  # the worker runs this very copy of surgtrack
        paths = [package_root, os.environ.get("PYTHONPATH", "")]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in paths if p)}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "surgtrack.sdf_worker", str(worker_in), str(worker_out)],
            pass_fds=(worker_in, worker_out), env=env,
        )
        os.close(worker_in)
        os.close(worker_out)
        self.send = Connection(to_worker, readable=False)
        self.recv = Connection(from_worker, writable=False)
        # the thread sends the start: the worker is still starting, and the pipe holds only 64 kB
        self.thread = threading.Thread(target=self.run, args=(start,), name="sdf-fitter", daemon=True)
        self.thread.start()

    def shutdown(self) -> None:
        """Stop the worker at once (a fit in progress is dropped) and the thread with it."""
        with self.cond:
            self.stop = True
            self.pending = None
            self.cond.notify_all()
        self.process.kill()
        self.process.wait()
        if threading.current_thread() is not self.thread:
            self.thread.join()
        self.send.close()
        self.recv.close()

    def run(self, start: tuple) -> None:
        """Send the worker its start, then each request, and take in each field it sends back."""
        try:
            self.send.send(start)
        except OSError as exc:
            self.died(exc)
            return
        del start  # the start state (MBs) is not held for the thread's life
        while True:
            with self.cond:
                self.cond.wait_for(lambda: self.stop or self.pending is not None)
                if self.stop:
                    return
                views, self.pending = self.pending, None
                self.busy = True
            try:
                self.send.send(views)
                state, poses, losses, report, error = self.recv.recv()
                if error is not None:
                    self.error = error
                else:
                    field = InstrumentSDF.from_state_dict(state, device=self.device)
                    field.refined_poses, field.last_losses = poses, losses
                    self.last_report = report
                    self.latest = field
                    self.fits_done += 1
            except (EOFError, OSError) as exc:
                self.died(exc)
                return
            finally:
                with self.cond:
                    self.busy = False
                    self.cond.notify_all()

    def died(self, exc: BaseException) -> None:
        """The worker is gone: stopped by `shutdown`, or it died (then reported through ``error``; later requests
        are dropped and the tracker goes on with the last field)."""
        with self.cond:
            if not self.stop:
                self.error = RuntimeError(f"the SDF fitting process stopped ({exc!r})")
            self.dead = True
            self.pending = None
            self.cond.notify_all()
