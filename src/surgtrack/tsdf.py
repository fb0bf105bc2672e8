"""Keyframe views, per-pixel evidence classes and the TSDF fusion that initialises the Instrument SDF.

Every pixel of a keyframe falls in one class (`classify_pixels`), which decides what its ray says about the field:

- SURF: instrument pixel with valid depth d: a surface at d (eq. 3, V_surf); free space in front of it.
- SEEN: non-instrument pixel with valid depth d: free space in front of d. Behind d the ray is blocked, so an
  occluder (a hand in front of the instrument) says nothing about what lies behind it: those samples are the
  candidates for V_occ (eq. 2). With occlusion handling off (``occ_surf=False``) the whole ray is taken as free
  space, as a mask-supervised fit without occlusion reasoning does, so occluders carve the instrument.
- HOLE: invalid depth on the instrument mask or within ``occ_dilate`` pixels of it (stereo shadow, specular metal,
  occluder boundary): unknown, candidates for V_occ. Without occlusion handling the off-mask ones are free space.
- EMPTY: invalid depth away from the instrument: free space along the whole ray.

Psi is signed: positive outside the instrument (towards the camera), negative inside, in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

SURF, SEEN, HOLE, EMPTY = 0, 1, 2, 3


@dataclass
class View:
    """One posed keyframe: depth (H, W) float32 metres with 0 invalid, instrument mask (H, W) bool, intrinsics 3x3,
    pose 4x4 object-to-camera (x_cam = pose @ x_obj), and an id (the keyframe's frame id) for refined poses."""

    depth: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    pose: np.ndarray
    id: str = ""


def pick_device(device: str | torch.device | None = None) -> torch.device:
    """The requested device, else CUDA when torch sees one, else CPU."""
    if device is not None:
        return torch.device(device)
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def classify_pixels(view: View, occ_dilate: int) -> np.ndarray:
    """Per-pixel evidence class (SURF, SEEN, HOLE, EMPTY) of a view, int8 (H, W)."""
    valid = view.depth > 0
    mask = view.mask.astype(bool)
    near = mask
    if occ_dilate > 0:
        near = ndimage.binary_dilation(mask, iterations=int(occ_dilate))
    codes = np.full(view.depth.shape, EMPTY, dtype=np.int8)
    codes[valid & ~mask] = SEEN
    codes[~valid & near] = HOLE
    codes[valid & mask] = SURF
    return codes


def occluder_pixels(view: View, truncation: float) -> np.ndarray:
    """Non-instrument pixels whose depth is within the instrument's depth range of the view (H, W) bool: what hides
    part of the instrument rather than lies behind it."""
    mask = view.mask.astype(bool)
    inst = view.depth[mask & (view.depth > 0)]
    if inst.size == 0:
        return np.zeros(view.depth.shape, dtype=bool)
    return ~mask & (view.depth > 0) & (view.depth < inst.max() + truncation)


@dataclass
class Grid:
    """Axis-aligned dense voxel lattice in the grid's frame (the object frame, or a rotation of it that
    `InstrumentSDF` keeps): node (i, j, k) sits at origin + voxel * (i, j, k)."""

    origin: np.ndarray  # (3,) metres
    voxel: float  # metres
    shape: tuple[int, int, int]  # (nx, ny, nz)

    @classmethod
    def around(cls, center: np.ndarray, extent: float | np.ndarray, voxel: float) -> Grid:
        """Lattice covering a box of side(s) `extent` centred on `center`."""
        ext = np.broadcast_to(np.asarray(extent, dtype=np.float64), (3,))
        n = np.maximum(np.ceil(ext / voxel).astype(int) + 1, 2)
        origin = np.asarray(center, dtype=np.float64) - (n - 1) * voxel / 2
        return cls(origin=origin, voxel=float(voxel), shape=(int(n[0]), int(n[1]), int(n[2])))

    @property
    def upper(self) -> np.ndarray:
        return self.origin + (np.array(self.shape) - 1) * self.voxel

    def nodes(self, device: torch.device) -> torch.Tensor:
        """(nx*ny*nz, 3) node positions, x-major (matching a (nx, ny, nz) array reshaped)."""
        axes = [
            torch.arange(n, device=device, dtype=torch.float32) * self.voxel + float(o)
            for n, o in zip(self.shape, self.origin, strict=True)
        ]
        gx, gy, gz = torch.meshgrid(*axes, indexing="ij")
        return torch.stack([gx, gy, gz], dim=-1).reshape(-1, 3)


def fuse_tsdf(
    views: list[View], grid: Grid, truncation: float, occ_surf: bool, occ_dilate: int, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted-average TSDF of the views on the grid (the initialisation of Psi).

    Returns (psi, weight), both (nx, ny, nz) float32 on `device`; psi is in units of `truncation`, clamped to
    [-1, 1]. Nodes no ray observed are inside (-1) when some view sees them behind an instrument surface, behind
    an occluder (`occluder_pixels`) or on a HOLE ray, outside (+1) otherwise (e.g. behind the table).
    """
    pts = grid.nodes(device)
    n = pts.shape[0]
    acc = torch.zeros(n, device=device)
    wsum = torch.zeros(n, device=device)
    behind = torch.zeros(n, device=device, dtype=torch.bool)
    for view in views:
        h, w = view.depth.shape
        codes = torch.as_tensor(classify_pixels(view, occ_dilate), device=device).reshape(-1)
        depth = torch.as_tensor(view.depth, device=device, dtype=torch.float32).reshape(-1)
        on_mask = torch.as_tensor(view.mask, device=device, dtype=torch.bool).reshape(-1)
        T = torch.as_tensor(view.pose, device=device, dtype=torch.float32)
        K = torch.as_tensor(view.K, device=device, dtype=torch.float32)
        pc = pts @ T[:3, :3].T + T[:3, 3]
        z = pc[:, 2]
        zs = torch.where(z > 1e-6, z, torch.ones_like(z))
        u = torch.round(K[0, 0] * pc[:, 0] / zs + K[0, 2]).long()
        v = torch.round(K[1, 1] * pc[:, 1] / zs + K[1, 2]).long()
        inb = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        pix = torch.where(inb, v * w + u, torch.zeros_like(u))
        c = codes[pix]
        sdf = (depth[pix] - z) / truncation
        surf = inb & (c == SURF) & (sdf > -1)
        if occ_surf:
            free = inb & (((c == SEEN) & (sdf > 1)) | (c == EMPTY))
        else:
            free = inb & ((c == SEEN) | (c == EMPTY) | ((c == HOLE) & ~on_mask[pix]))
        acc += torch.where(surf, sdf.clamp(max=1.0), torch.zeros_like(sdf)) + free.float()
        wsum += surf.float() + free.float()
        occluder = occluder_pixels(view, truncation)
        occluder = torch.as_tensor(occluder, device=device).reshape(-1)[pix]
        behind |= inb & ((on_mask[pix] & ((c != SURF) | (sdf <= -1))) | (occluder & (sdf <= -1)) | (c == HOLE))
    psi = torch.where(wsum > 0, acc / wsum.clamp(min=1e-9), torch.where(behind, -1.0, 1.0))
    return psi.reshape(grid.shape), wsum.reshape(grid.shape)
