"""Frame preprocessing (Stage 2, step 1): depth filtering, normals, grazing-angle rejection, masked point cloud.

All work happens inside a crop around the instrument mask, so the cost follows the instrument's size on screen,
not the image size.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .config import PreprocessConfig
from .geometry import depth_to_xy
from .io import Frame


@dataclass
class Observation:
    """A preprocessed frame: filtered depth, per-pixel points and normals, and the instrument's valid pixels, held in
    the crop ``box`` around the mask (every pixel outside it is invalid); the whole image's arrays are made on first
    use."""

    frame: Frame
    mask: np.ndarray  # (H, W) bool: the instrument mask used (before depth checks)
    box: tuple[slice, slice]  # the crop's rows and columns in the image
    crop_depth: np.ndarray  # (h, w) float32 metres, filtered; 0 = invalid
    crop_xyz: np.ndarray  # (h, w, 3) float32 camera-frame points
    crop_normals: np.ndarray  # (h, w, 3) float32 camera-frame unit normals (0 where unknown)
    crop_valid: np.ndarray  # (h, w) bool: instrument pixel with trusted depth and normal
    crop_trusted: np.ndarray  # (h, w) bool: trusted depth and normal, on the mask or not (`remasked`)
    mask_given: bool = True  # the mask came with the frame (False: predicted from the model or a colour region)

    @property
    def K(self) -> np.ndarray:
        return self.frame.K

    @property
    def shape(self) -> tuple[int, int]:
        """The image's (H, W)."""
        return self.mask.shape

    @cached_property
    def n_valid(self) -> int:
        return int(self.crop_valid.sum())

    def _whole(self, crop: np.ndarray) -> np.ndarray:
        out = np.zeros(self.shape + crop.shape[2:], crop.dtype)
        out[self.box] = crop
        return out

    @cached_property
    def depth(self) -> np.ndarray:
        """(H, W) float32 filtered depth, 0 = invalid."""
        return self._whole(self.crop_depth)

    @cached_property
    def xyz(self) -> np.ndarray:
        """(H, W, 3) camera-frame points."""
        return self._whole(self.crop_xyz)

    @cached_property
    def normals(self) -> np.ndarray:
        """(H, W, 3) camera-frame unit normals (0 where unknown)."""
        return self._whole(self.crop_normals)

    @cached_property
    def valid(self) -> np.ndarray:
        """(H, W) bool: instrument pixel with trusted depth and normal."""
        return self._whole(self.crop_valid)

    @cached_property
    def mask_edge(self) -> MaskEdge:
        """`MaskEdge` of the mask, built once: every posture graph solve of the frame reads it (L_FS)."""
        return MaskEdge.of(self.mask)

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """The masked point cloud and its normals, camera frame (row-major pixel order)."""
        return self.crop_xyz[self.crop_valid], self.crop_normals[self.crop_valid]

    def at(self, v: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Whether each image pixel (v, u) is valid, and the points and normals of those that are."""
        rs, cs = self.box
        i, j = v - rs.start, u - cs.start
        h, w = self.crop_valid.shape
        ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
        ok[ok] = self.crop_valid[i[ok], j[ok]]
        return ok, self.crop_xyz[i[ok], j[ok]], self.crop_normals[i[ok], j[ok]]

    def grid(self, factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points and normals on the image's grid downscaled by ``factor`` (grid pixel i is image pixel i * factor;
        z = 0 outside the instrument), and its K."""
        (h, w), (rs, cs) = self.shape, self.box
        xyz = np.zeros((-(-h // factor), -(-w // factor), 3), self.crop_xyz.dtype)
        nrm = np.zeros_like(xyz)
        r0, c0 = -(-rs.start // factor), -(-cs.start // factor)  # the first grid row and column in the crop
        r1, c1 = -(-rs.stop // factor), -(-cs.stop // factor)
        sub = (slice(r0 * factor - rs.start, None, factor), slice(c0 * factor - cs.start, None, factor))
        v = self.crop_valid[sub]
        xyz[r0:r1, c0:c1][v] = self.crop_xyz[sub][v]
        nrm[r0:r1, c0:c1][v] = self.crop_normals[sub][v]
        K = self.K.copy()
        K[:2] /= factor
        return xyz, nrm, K


def mask_bbox(mask: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """Bounding box of a mask grown by ``margin`` pixels, clipped to the image; None for an empty mask."""
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    if rows.size == 0:
        return None
    h, w = mask.shape
    return (
        slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, h)),
        slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, w)),
    )


def normals_from_planes(x: np.ndarray, y: np.ndarray, z: np.ndarray, step: int = 2) -> tuple[np.ndarray, ...]:
    """Unit normals of the points whose component planes are x, y, z (each (H, W)), as their three planes: the
    cross product of central differences ``step`` pixels apart, facing the camera (0 at the border and where the
    differences are parallel)."""

    def diff(a: np.ndarray, axis: int) -> np.ndarray:
        out = np.zeros_like(a)
        if axis == 1:
            np.subtract(a[:, 2 * step :], a[:, : -2 * step], out=out[:, step:-step])
        else:
            np.subtract(a[2 * step :], a[: -2 * step], out=out[step:-step])
        return out

    ax, ay, az = diff(x, 1), diff(y, 1), diff(z, 1)
    bx, by, bz = diff(x, 0), diff(y, 0), diff(z, 0)
    n = (ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)
    norm = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    ok = norm > 0
    for c in n:
        np.divide(c, norm, out=c, where=ok)
        c[~ok] = 0
    flip = n[0] * x + n[1] * y + n[2] * z > 0
    for c in n:
        np.negative(c, out=c, where=flip)
    return n


@dataclass(frozen=True)
class MaskEdge:
    """A mask and its edge pixels (mask pixels with a neighbour off it) in a k-d tree: the mask pixel nearest to a
    point off the mask is an edge pixel, so distances to the mask cost a query of the edge, not a distance
    transform of the image."""

    mask: np.ndarray  # (H, W) bool
    uv: np.ndarray  # (B, 2) edge pixels' (u, v)
    tree: cKDTree | None  # over uv; None without edge pixels

    @classmethod
    def of(cls, mask: np.ndarray) -> MaskEdge:
        mask = np.asarray(mask, dtype=bool)
        box = mask_bbox(mask, margin=1)
        if box is None:
            return cls(mask, np.zeros((0, 2)), None)
        m = mask[box].astype(np.uint8)
        rows, cols = np.nonzero(m & ~cv2.erode(m, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE))
        uv = np.column_stack([cols + box[1].start, rows + box[0].start]).astype(np.float64)
        return cls(mask, uv, cKDTree(uv) if len(uv) else None)

    def distance(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance in pixels from the points (u, v), off the mask, to the nearest mask pixel's centre, and its
        gradient (d/du, d/dv): the unit vector from that pixel to the point. Infinite without an edge."""
        if self.tree is None:
            return np.full(len(u), np.inf), np.zeros(len(u)), np.zeros(len(u))
        dist, j = self.tree.query(np.column_stack([u, v]))
        q = self.uv[j]
        n = np.maximum(dist, 1e-9)
        return dist, (u - q[:, 0]) / n, (v - q[:, 1]) / n


def crop_box(mask: np.ndarray, cfg: PreprocessConfig) -> tuple[slice, slice]:
    """The crop `preprocess` works in: the mask's box, grown by the bilateral filter's reach and the normals'."""
    return mask_bbox(mask, margin=max(cfg.bilateral_d, 2) + 2) or (slice(0, 0), slice(0, 0))


def _mask_pixels(mask: np.ndarray, box: tuple[slice, slice], cfg: PreprocessConfig) -> np.ndarray:
    """The mask in the crop, eroded by ``cfg.mask_erosion`` pixels, as bool."""
    m = mask[box].astype(np.uint8)
    if cfg.mask_erosion > 0 and m.size:
        m = cv2.erode(m, np.ones((2 * cfg.mask_erosion + 1,) * 2, np.uint8))
    return m > 0


def remasked(obs: Observation, mask: np.ndarray, cfg: PreprocessConfig) -> Observation:
    """``obs``'s frame preprocessed with another ``mask``, the same as `preprocess` gives: when the mask's crop is
    ``obs``'s, the filtered depth, points and normals are those of ``obs`` (they depend on the crop only) and only
    the mask's pixels are found again."""
    box = crop_box(mask, cfg)
    if box != obs.box:
        return preprocess(obs.frame, mask, cfg, obs.mask_given)
    valid = obs.crop_trusted & _mask_pixels(mask, box, cfg)
    return Observation(obs.frame, mask, box, obs.crop_depth, obs.crop_xyz, obs.crop_normals, valid, obs.crop_trusted,
                       obs.mask_given)


def preprocess(frame: Frame, mask: np.ndarray, cfg: PreprocessConfig, mask_given: bool = True) -> Observation:
    """Filter depth, compute normals and keep instrument pixels with trustworthy geometry, in a crop around the mask;
    ``mask_given`` says whether ``mask`` came with the frame. Worked on one component plane at a time."""
    box = crop_box(mask, cfg)
    rs, cs = box
    d = frame.depth[rs, cs].astype(np.float32)
    d = np.where((d > cfg.min_depth) & (d < cfg.max_depth), d, np.float32(0))
    good = d > 0
    if cfg.bilateral_d > 0 and d.size:
        f = cv2.bilateralFilter(d, cfg.bilateral_d, cfg.bilateral_sigma_depth, cfg.bilateral_sigma_space)
        # The filter mixes in invalid zeros at hole borders: keep only pixels it changed little.
        good &= np.abs(f - d) < 3 * cfg.bilateral_sigma_depth
        d = np.where(good, f, np.float32(0))
    x, y = (c.astype(np.float32) for c in depth_to_xy(d, frame.K, (rs.start, cs.start)))
    n = normals_from_planes(x, y, d, cfg.normal_step)
    # A normal is trusted only where the neighbours it is made from have depth on the same surface.
    k = cfg.normal_step
    dn = np.zeros_like(good)
    c = (slice(k, -k), slice(k, -k))
    up, down, left, right = (slice(None, -2 * k), c[1]), (slice(2 * k, None), c[1]), (c[0], slice(None, -2 * k)), (
        c[0], slice(2 * k, None))
    dn[c] = good[c] & good[up] & good[down] & good[left] & good[right]
    dn[c] &= (np.abs(d[up] - d[down]) < 0.02) & (np.abs(d[left] - d[right]) < 0.02)
    length = np.maximum(np.sqrt(x * x + y * y + d * d), np.float32(1e-9))
    cos = -((x / length) * n[0] + (y / length) * n[1] + (d / length) * n[2])  # the normal against the viewing ray
    trusted = dn & (cos > np.cos(np.radians(cfg.max_grazing_deg)))
    ok = trusted & _mask_pixels(mask, box, cfg)
    return Observation(frame, mask, box, d, np.stack([x, y, d], axis=-1), np.stack(n, axis=-1), ok, trusted,
                       mask_given)
