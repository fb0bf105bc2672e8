"""Instrument masks for frames that come without one: render the model at the predicted pose, keep the pixels whose
observed depth agrees, and leave out occluders in front."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from .geometry import backproject, depth_to_xyz, inv_T, off_line, project, span, transform

SPLAT = 2  # pixels each model point covers around its projection (render_depth)


def render_depth(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, shape: tuple[int, int],
                 splat: int = SPLAT) -> np.ndarray:
    """Z-buffered depth of model points seen at ``pose`` (0 where nothing projects); points are splatted to
    (2 * splat + 1)^2 pixels so a sparse model renders as a closed surface."""
    box, crop = render_box(points_obj, pose, K, shape, splat)
    depth = np.zeros(shape, np.float32)
    depth[box] = crop
    return depth


def render_box(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, shape: tuple[int, int],
               splat: int = SPLAT, pad: int = 0) -> tuple[tuple[slice, slice], np.ndarray]:
    """`render_depth` in the box around the projections grown by the splat and ``pad`` more pixels (clipped to the
    image; nothing renders outside it): the box's rows and columns, and the depth in it (empty when nothing
    projects)."""
    h, w = shape
    p = transform(pose, points_obj)
    p = p[p[:, 2] > 1e-3]
    uv, z = project(p, K)
    u = np.round(uv[:, 0]).astype(int)
    v = np.round(uv[:, 1]).astype(int)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[inside], v[inside], z[inside]
    if len(z) == 0:
        return (slice(0, 0), slice(0, 0)), np.zeros((0, 0), np.float32)
    grow = splat + pad
    u0, v0 = max(int(u.min()) - grow, 0), max(int(v.min()) - grow, 0)
    u1, v1 = min(int(u.max()) + grow + 1, w), min(int(v.max()) + grow + 1, h)
    box = np.full((v1 - v0, u1 - u0), np.inf, np.float32)
    np.minimum.at(box, (v - v0, u - u0), z.astype(np.float32))
    if splat > 0:
        box = -cv2.dilate(-box, np.ones((2 * splat + 1,) * 2, np.uint8))  # min filter
    box[box >= np.finfo(np.float32).max] = 0  # the min filter pads the border with float32 max
    box[~np.isfinite(box)] = 0
    return (slice(v0, v1), slice(u0, u1)), box


def silhouette_core(model: np.ndarray) -> np.ndarray:
    """The model's silhouette in a `render_depth` image without the splat's own rim (eroded away)."""
    return cv2.erode((model > 0).astype(np.uint8), np.ones((2 * SPLAT + 1,) * 2, np.uint8)).astype(bool)


def predict_mask(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, depth: np.ndarray,
                 margin: int, tol: float, rgb: np.ndarray | None = None, colour: ColourModel | None = None,
                 min_posterior: float = 0.0, front_tol: float | None = None, keep: float = 0.8,
                 inside_posterior: float = 0.0, grow_posterior: float = 0.0, grow_step: float = 0.01,
                 grow_ratio: float = 2.0) -> np.ndarray:
    """Mask of the instrument at a predicted pose: observed depth within ``tol`` of the model's depth nearby.

    The model depth is spread over ``margin`` pixels to absorb the prediction's error; observed depth more than
    ``tol`` in front of the model (an occluder) or behind it (background) is left out. With ``front_tol`` the mask
    stops that much in front of the model (a finger lying on the shaft is nearer by little more than its own
    thickness) unless that would lose more than 1 - ``keep`` of it (the instrument itself came nearer since the
    pose was predicted). With a ``colour`` model (and the frame's ``rgb``), the pixels beyond the rendered model's
    own silhouette must also have a colour posterior of at least ``min_posterior``, so the mask grows into neither
    a hand nor tissue at the instrument's depth, and those inside it at least ``inside_posterior`` (0: not looked
    up), so fingers touching the instrument, within the depth window, stay out too. With ``grow_posterior`` > 0 the
    mask then grows into the parts the model does not have yet (`grow_mask`)."""
    # Worked in the box the model renders to, grown by the margin and the silhouette's erosion: nothing beyond it.
    box, model = render_box(points_obj, pose, K, depth.shape, pad=margin + SPLAT)
    whole = np.zeros(depth.shape, bool)
    if not (model > 0).any():
        return whole
    kernel = np.ones((2 * margin + 1,) * 2, np.uint8)
    zmin = -cv2.dilate(-np.where(model > 0, model, np.float32(1e3)), kernel)
    zmax = cv2.dilate(model, kernel)
    d = depth[box]
    mask = (zmax > 0) & (d > 0) & (d > zmin - tol) & (d < zmax + tol)
    if front_tol is not None:
        tight = mask & (d > zmin - front_tol)
        if tight.sum() >= keep * mask.sum():
            mask = tight
    if colour is not None and rgb is not None:
        core = silhouette_core(model)
        looked = mask & ~core if inside_posterior <= 0 else mask.copy()
        least = np.where(core[looked], inside_posterior, min_posterior)
        mask[looked] = colour.posterior(rgb[box][looked]) >= least
    whole[box] = mask
    if colour is not None and rgb is not None and grow_posterior > 0 and mask.any():
        whole = grow_mask(whole, depth, colour.posterior(rgb) >= grow_posterior, grow_step, grow_ratio)
    return whole


def grow_mask(mask: np.ndarray, depth: np.ndarray, candidates: np.ndarray, step: float, ratio: float) -> np.ndarray:
    """``mask`` grown into the ``candidates`` (instrument-coloured pixels with valid depth) connected to it without a
    depth jump of more than ``step`` (m): the length of a shaft that the model has not seen yet. Growth of more than
    ``ratio`` times the mask's own area (the instrument's colour spilling over tissue or a drape) is not taken."""
    grown = (candidates & (depth > 0) & ~_depth_edges(depth, step)) | mask
    _, labels = cv2.connectedComponents(grown.astype(np.uint8), connectivity=4)
    touched = np.unique(labels[mask])
    added = np.isin(labels, touched[touched > 0]) & ~mask
    if added.sum() > ratio * mask.sum():
        return mask
    return mask | added


def grow_region(region: np.ndarray, depth: np.ndarray, posterior: np.ndarray, min_posterior: float, reach: int,
                step: float) -> np.ndarray:
    """A search region (`search_regions`) grown (`grow_mask`) into the pixels within ``reach`` pixels of it whose
    colour posterior is at least ``min_posterior``, connected to it without a depth jump of more than ``step`` (m).
    The instrument's most certain colours can lie where the sensor drops the depth (bright, specular metal), and its
    parts with depth show colours the first frame did not (a posterior near 0.5): the region alone then holds too
    few points to re-localise on."""
    near = cv2.dilate(region.astype(np.uint8), np.ones((2 * reach + 1,) * 2, np.uint8)).astype(bool)
    return grow_mask(region, depth, near & (posterior >= min_posterior), step, np.inf)


def within_reach(mask: np.ndarray, depth: np.ndarray, K: np.ndarray, pose: np.ndarray,
                 axis: tuple[np.ndarray, np.ndarray, float], margin: float) -> np.ndarray:
    """``mask`` without the pixels whose points, in the object frame at ``pose``, lie further than the reach plus
    ``margin`` (m) from the instrument's long ``axis`` (centre, unit direction, reach; `tracker.long_axis`): a hand
    holding the shaft at its depth."""
    pts, vu = backproject(depth, K, mask)
    centre, direction, reach = axis
    far = vu[off_line(transform(inv_T(pose), pts), centre, direction) > reach + margin]
    out = mask.copy()
    out[far[:, 0], far[:, 1]] = False
    return out


RING_INNER = 6  # px: the colour model's surroundings start this far from the first mask (its edge blurs both)


class ColourModel:
    """Instrument vs. surroundings colour likelihoods for masks predicted without a given mask.

    Two smoothed histograms over quantised RGB, both from the first frame: the instrument's from its given mask,
    the surroundings' from a ring from `RING_INNER` to ``ring`` pixels around it, where the hands holding the
    instrument and the tissue beside it are. Bayes' rule with equal priors gives each pixel's posterior of being
    instrument. The ring reaches far (120 px) because the hand that later touches the instrument is often further
    away in the first frame, and the bins are fine (32 a channel) because a pale glove and bright steel share
    coarser ones. (Refreshing the surroundings from later frames was measured to hurt: the ring then takes in parts
    of the instrument the model has not seen yet. What lies well in front of the model at a tracked pose cannot be
    the instrument, and `add_surroundings` takes it in.)"""

    def __init__(self, bins: int = 32, ring: int = 120):
        self.bins, self.ring = bins, ring
        self.instrument: np.ndarray | None = None
        self.surroundings: np.ndarray | None = None
        self._counts: np.ndarray | None = None  # the surroundings' raw counts, which `add_surroundings` extends

    def _index(self, rgb: np.ndarray) -> np.ndarray:
        q = (rgb.astype(np.int32) * self.bins) >> 8
        return (q[..., 0] * self.bins + q[..., 1]) * self.bins + q[..., 2]

    def _count(self, rgb: np.ndarray, where: np.ndarray) -> np.ndarray:
        return np.bincount(self._index(rgb)[where], minlength=self.bins ** 3).astype(np.float64)

    def _histogram(self, counts: np.ndarray) -> np.ndarray:
        h = gaussian_filter(counts.reshape((self.bins,) * 3), 1.0, mode="constant").ravel()
        return h / max(h.sum(), 1e-12)

    def _ring(self, mask: np.ndarray) -> np.ndarray:
        def grow(r: int) -> np.ndarray:
            return cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1,) * 2))

        return grow(self.ring).astype(bool) & ~grow(RING_INNER).astype(bool)

    def learn(self, rgb: np.ndarray, mask: np.ndarray) -> None:
        """Start from a given instrument mask: its pixels are instrument, a ring around it surroundings."""
        self.instrument = self._histogram(self._count(rgb, mask.astype(bool)))
        self._counts = self._count(rgb, self._ring(mask))
        self.surroundings = self._histogram(self._counts)

    def add_surroundings(self, rgb: np.ndarray, where: np.ndarray) -> None:
        """Pixels known not to be the instrument (an occluder in front of it at a tracked pose) join the
        surroundings: a glove first seen on the instrument later stays out of the mask beside it too."""
        if self._counts is None or not where.any():
            return
        self._counts = self._counts + self._count(rgb, where)
        self.surroundings = self._histogram(self._counts)

    def posterior(self, rgb: np.ndarray) -> np.ndarray:
        """P(instrument | colour) for each RGB triple of ``rgb`` (..., 3), equal priors (0.5 where neither
        histogram has seen the colour, and before `learn`)."""
        eps = 0.5 / self.bins ** 3  # half a uniform bin: a colour neither histogram has seen stays near 0.5
        if self.instrument is None or self.surroundings is None:
            return np.full(rgb.shape[:-1], 0.5)
        f = self.instrument[self._index(rgb)] + eps
        b = self.surroundings[self._index(rgb)] + eps
        return f / (f + b)


def _depth_edges(depth: np.ndarray, step: float) -> np.ndarray:
    """Pixels with valid depth lying more than ``step`` (m) behind a 4-neighbour with valid depth: the far side of
    each depth jump, so a nearer object keeps its outline and one behind it is cut off from it."""
    edge = np.zeros(depth.shape, bool)
    pair = (depth[1:] > 0) & (depth[:-1] > 0)  # vertical neighbours
    edge[1:] |= pair & (depth[1:] - depth[:-1] > step)
    edge[:-1] |= pair & (depth[:-1] - depth[1:] > step)
    pair = (depth[:, 1:] > 0) & (depth[:, :-1] > 0)  # horizontal neighbours
    edge[:, 1:] |= pair & (depth[:, 1:] - depth[:, :-1] > step)
    edge[:, :-1] |= pair & (depth[:, :-1] - depth[:, 1:] > step)
    return edge


def search_regions(posterior: np.ndarray, depth: np.ndarray, K: np.ndarray, centre: np.ndarray, radius: float,
                   min_posterior: float, pixels: tuple[int, int], n: int = 1,
                   depth_step: float = 0.01, max_span: float = np.inf) -> list[np.ndarray]:
    """Where the instrument may be when its pose is lost: the connected regions of pixels whose colour is
    instrument with at least ``min_posterior``, of a plausible pixel count (``pixels``: min, max, counting pixels
    with valid depth) and width (at most ``max_span``, m: the `geometry.span` of its pixels across the view at their
    median depth, which a few pixels of the background behind its edge do not set; a wall far behind can show as
    few pixels as the instrument near), whose 3D centroid lies within ``radius`` of ``centre``
    (camera frame: where the instrument was last seen); the ``n`` nearest to it, nearest first, each as its pixels
    with valid depth.
    Connectivity is by colour alone, so depth dropouts along a thin shaft do not break it apart; a region too large
    (the instrument's merged with a hand, drape or tissue of a similar colour) is cut again, 4-connected, where the
    depth is missing or jumps by more than ``depth_step`` (the far side of the jump is cut off, so a diagonal
    contact does not join them), and its pieces compete with the other regions."""
    labels, area = _regions(posterior >= min_posterior, depth, 8)
    xyz = depth_to_xyz(depth, K)
    near = _near(labels, area, xyz, centre, radius, pixels, max_span)
    too_big = np.flatnonzero(area[1:] > pixels[1]) + 1
    if len(too_big):
        pieces, piece_area = _regions(np.isin(labels, too_big) & ~_depth_edges(depth, depth_step), depth, 4)
        near += _near(pieces, piece_area, xyz, centre, radius, pixels, max_span)
    near.sort(key=lambda found: found[0])
    return [region for _, region in near[:n]]


def _regions(candidates: np.ndarray, depth: np.ndarray, connectivity: int) -> tuple[np.ndarray, np.ndarray]:
    """The connected regions of ``candidates`` as a label image (0: none, or no valid depth) and their areas in
    pixels with valid depth."""
    count, labels = cv2.connectedComponents(candidates.astype(np.uint8), connectivity=connectivity)
    labels[depth <= 0] = 0
    return labels, np.bincount(labels.ravel(), minlength=count)


def _near(labels: np.ndarray, area: np.ndarray, xyz: np.ndarray, centre: np.ndarray, radius: float,
          pixels: tuple[int, int], max_span: float) -> list[tuple[float, np.ndarray]]:
    """`search_regions`' regions of a plausible size within ``radius``, with their centroids' distances."""
    near = []
    for label in np.flatnonzero((area >= pixels[0]) & (area <= pixels[1])):
        if label == 0:
            continue
        region = labels == label
        points = xyz[region]
        middle = np.median(points, axis=0)
        distance = float(np.linalg.norm(middle - centre))
        if distance <= radius and span(points[:, :2] / points[:, 2:] * middle[2]) <= max_span:
            near.append((distance, region))
    return near


def seen_past(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, depth: np.ndarray, tol: float) -> float:
    """Share of the model's silhouette at ``pose`` (`silhouette_core`) where the frame's depth lies more
    than ``tol`` behind the model: the camera saw through where the pose puts the instrument. Pixels with nothing
    seen, or something more than ``tol`` in front of the model (an occluder), are left out."""
    box, model = render_box(points_obj, pose, K, depth.shape, pad=SPLAT)  # room for silhouette_core's erosion
    if model.size == 0:
        return 0.0
    depth = depth[box]
    core = silhouette_core(model) & (depth > 0) & (depth > model - tol)
    n = int(core.sum())
    return float((depth[core] > model[core] + tol).sum()) / n if n else 0.0


def silhouette_iou(points_obj: np.ndarray, pose: np.ndarray, K: np.ndarray, mask: np.ndarray) -> float:
    """Intersection over union of the model's silhouette at ``pose`` (`render_depth`) and ``mask``: low when a
    pose fits the frame's points to one part of the model and the rest of it would show where nothing was seen.
    Rendered in the model's box (`render_box`): the mask beyond it counts towards the union only."""
    box, model = render_box(points_obj, pose, K, mask.shape)
    outline = model > 0
    inside = int(np.count_nonzero(outline & (mask[box] != 0)))
    union = int(np.count_nonzero(outline)) + int(np.count_nonzero(mask)) - inside
    return inside / union if union else 0.0
