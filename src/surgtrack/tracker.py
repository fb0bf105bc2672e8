"""SurgTracker: the per-frame tracking step (Stage 2) over a posture memory pool and a posture graph.

    tracker = SurgTracker(TrackerConfig())
    pose = tracker.register(frame, mask)          # first frame: fixes the object frame
    result = tracker.track(frame, mask=None)      # every later frame
    observed = tracker.observe(frame)             # a frame with its mask, ahead (another thread) ...
    result = tracker.track(frame, frame.mask, observed)  # ... then tracked: the same result as track(frame, mask)

The object frame has its origin at the centre of the first frame's masked point cloud (outliers removed) and axes
parallel to the first camera's; poses are object-to-camera (x_cam = pose @ x_obj), metres.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from .appearance import intensity, keyframe_ncc, sample
from .config import GraphConfig, SDFConfig, TrackerConfig
from .features import FeatureExtractor, Features, match
from .geometry import (
    backproject,
    inv_T,
    make_T,
    off_line,
    orthonormalize,
    project,
    rotation_angle_deg,
    span,
    transform,
    voxel_downsample,
)
from .global_registration import FpfhCloud, global_register, icp_from
from .io import Frame
from .masking import (
    ColourModel,
    grow_region,
    predict_mask,
    render_box,
    search_regions,
    seen_past,
    silhouette_iou,
    within_reach,
)
from .memory_pool import Keyframe, MemoryPool
from .model import InstrumentModel
from .posture_graph import Coverage, FeatureEdge, FreeSpace, GraphNode, GridPoints, Unmeasured, optimize_graph
from .preprocess import MaskEdge, Observation, preprocess, remasked
from .ransac import plausible, ransac_pose, within
from .registration import BackgroundFitter, InstrumentSDF
from .tsdf import View

TRACKED, LOST, RELOCALISED = "tracked", "lost", "relocalised"
# Why a frame was lost (TrackResult.reason):
HIDDEN = "hidden"  # fewer than failure.min_pixels instrument pixels in the mask: covered or out of view
NO_DEPTH = "no depth"  # the mask shows the instrument, but fewer than failure.min_pixels of it have trusted depth
NO_POSE = "no pose"  # no coarse pose, or no re-localisation candidate passed its checks
UNSURE = "unsure"  # fewer than failure.min_confidence of the frame's points lie on the model at the pose
SEEN_PAST = "seen past"  # the camera sees past the model at the pose (failure.max_seen_past)
NOT_TRIED = "not tried"  # lost before, no mask, and the search skips this frame (failure.relocalise_every)
COLOURS_KEPT = 10  # tracked frames whose made masks' colours a re-localisation is held to (`_looks_like_before`)
NEW_POINT_GAP = 0.004  # m: a keyframe's point this far from the model is new to it (`_probation_ends`)
PROBATION_MIN_POINTS = 10  # new points, and points seen, that judge a keyframe on probation


def unseen(mask: np.ndarray, min_pixels: int) -> str:
    """Why a frame whose mask gave too few trusted points is lost: `HIDDEN` when the mask itself has fewer than
    ``min_pixels`` pixels, else `NO_DEPTH` (the sensor's depth is missing or untrusted on the instrument)."""
    return HIDDEN if np.count_nonzero(mask) < min_pixels else NO_DEPTH


@dataclass
class TrackResult:
    """What track() returns: pose (None when lost), status, confidence in [0, 1], per-stage seconds, the feature
    inliers, whether the Instrument SDF's term L_SDF (eq. 11) was in the posture graph that gave the pose, for a
    lost frame why (`HIDDEN`, `NO_DEPTH`, `NO_POSE`, `UNSURE`, `SEEN_PAST` or `NOT_TRIED`; "" otherwise), and the
    directions of the pose that graph's data left free, held by the motion prior (`posture_graph.Unmeasured`: the
    turn about a round shaft, the slide along a bare one); for a posed frame tracked on a mask the tracker made,
    that mask's mean colour posterior (`SurgTracker._mask_colour`)."""

    pose: np.ndarray | None
    status: str
    confidence: float
    timings: dict[str, float] = field(default_factory=dict)
    inliers: int = 0
    sdf: bool = False
    reason: str = ""
    unmeasured: tuple[Unmeasured, ...] = ()
    colour: float | None = None  # a posed frame without a given mask: how instrument-like its made mask looks

    @property
    def unmeasured_kinds(self) -> list[str]:
        """The kinds among ``unmeasured`` ("slide", "turn"), sorted, each once."""
        return sorted({u.kind for u in self.unmeasured})


@dataclass(frozen=True)
class Observed:
    """A frame preprocessed with its given mask and its features (`SurgTracker.observe`; None when too few of its
    points are trusted to track on), and the seconds each took."""

    obs: Observation
    features: Features | None
    timings: dict[str, float]


@dataclass(eq=False)
class _Node:
    """A tracked frame as the graph and the pool see it."""

    frame_id: str
    index: int
    pose: np.ndarray
    features: Features
    xyz: np.ndarray
    normals: np.ndarray
    K_grid: np.ndarray
    distances: tuple[bytes, cKDTree | None, np.ndarray] | None = field(default=None, repr=False)  # of its pose
    sdf: bool = False  # L_SDF (eq. 11) was in the graph that gave its pose
    unmeasured: list[Unmeasured] = field(default_factory=list)  # what that graph's data left free

    @cached_property
    def grid_points(self) -> GridPoints:
        return GridPoints.of(self.xyz, self.normals)

    def graph_node(self, fixed: bool) -> GraphNode:
        return GraphNode(self.pose, self.xyz, self.normals, self.K_grid, fixed, self.grid_points)


class _Candidate(NamedTuple):
    """A re-localisation candidate after refinement: its node, `_fit_error`, `_appearance` and motion from the
    last tracked pose (m, plus 0.1 m a radian)."""

    node: _Node
    fit: float
    looks: float | None
    move: float


class _Clock:
    def __init__(self) -> None:
        self.t = time.perf_counter()
        self.laps: dict[str, float] = {}

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = self.laps.get(name, 0.0) + now - self.t
        self.t = now

    def add(self, laps: dict[str, float]) -> None:
        """Count stages timed elsewhere (another thread) in."""
        for name, seconds in laps.items():
            self.laps[name] = self.laps.get(name, 0.0) + seconds


def object_origin(points: np.ndarray) -> np.ndarray:
    """Centre of the first frame's masked cloud with outliers removed (points beyond 3 MADs of the median)."""
    med = np.median(points, axis=0)
    dist = np.linalg.norm(points - med, axis=1)
    mad = np.median(np.abs(dist - np.median(dist))) + 1e-6
    keep = dist < np.median(dist) + 3 * 1.4826 * mad
    return points[keep].mean(axis=0)


def field_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (the points' mean), orientation R (rows: their principal axes) and size (m, per axis) of the SDF's
    box around the first frame's preprocessed instrument points (flying pixels already dropped): 1.5 times what
    they show plus 4 cm, for parts seen later. The first frame shows one side only, so across the longest axis the
    box is at least as deep as the instrument is wide (its second extent). Along the principal axes an inclined,
    elongated instrument fills its box; an axis-aligned box around it is mostly empty voxels."""
    centre = points.mean(axis=0)
    _, vecs = np.linalg.eigh((points - centre).T @ (points - centre))
    R = vecs[:, ::-1].T  # rows by decreasing variance
    if np.linalg.det(R) < 0:
        R[2] *= -1
    size = np.ptp((points - centre) @ R.T, axis=0)
    size[2] = size[1]
    return centre, R, np.clip(1.5 * size + 0.04, 0.08, 0.6)


def shaft_range(psi: InstrumentSDF, points: np.ndarray, trim: float = 3.0, pad: float = 0.02,
                longest: float = 0.8) -> tuple[float, float]:
    """The range (m) along ``psi``'s first (longest) box axis, grid frame, that the final fit's box spans: its
    own, grown to the ``trim`` and 100 - ``trim`` percentiles, plus ``pad``, of the keyframes' object-frame
    ``points`` that lie within its cross-section; at most ``longest`` m. The first frame shows part of a shaft,
    later keyframes more of it; the percentiles keep a drifted keyframe's points from stretching the box."""
    lo, hi = float(psi.grid.origin[0]), float(psi.grid.upper[0])
    q = points @ psi.rotation.T
    across = ((q[:, 1:] >= psi.grid.origin[1:]) & (q[:, 1:] <= psi.grid.upper[1:])).all(axis=1)
    if across.any():
        a, b = np.percentile(q[across, 0], [trim, 100.0 - trim])
        lo, hi = min(lo, a - pad), max(hi, b + pad)
        excess = max(hi - lo - longest, 0.0)
        lo, hi = lo + excess / 2, hi - excess / 2
    return lo, hi


def long_axis(points: np.ndarray, share: float = 98.0) -> tuple[np.ndarray, np.ndarray, float]:
    """A line along an instrument and its reach across it: `field_box`'s centre and first principal axis of the
    points, and the ``share`` percentile of their distances from that line (m). From the first frame's masked points,
    the reach bounds how far from its shaft a mask predicted later may extend (`masking.within_reach`)."""
    centre, R, _ = field_box(points)
    return centre, R[0], float(np.percentile(off_line(points, centre, R[0]), share))


def new_field(cfg: SDFConfig, obs: Observation, origin: np.ndarray) -> InstrumentSDF:
    """An empty Instrument SDF in the box `field_box` sets around a first frame's preprocessed points, in the object
    frame whose origin (camera frame, axes the camera's) is ``origin``."""
    centre, R, extent = field_box(obs.points()[0])
    return InstrumentSDF(cfg, centre - origin, extent, rotation=R)


class SurgTracker:
    """Model-free 6-DoF tracker of one instrument."""

    def __init__(self, config: TrackerConfig | None = None, model: InstrumentModel | None = None):
        self.cfg = config or TrackerConfig()
        self.cfg.check()
        self.extractor = FeatureExtractor(self.cfg.ransac.features, self.cfg.ransac.max_keypoints)
        self._observer: FeatureExtractor | None = None  # observe()'s own: the extractor keeps its last detection
        self.pool = MemoryPool(self.cfg.pool)
        self.rng = np.random.default_rng(self.cfg.seed)
        self.recent: deque[_Node] = deque(maxlen=max(self.cfg.graph.adjacent, 1))
        self.colours: deque[float] = deque(maxlen=COLOURS_KEPT)  # of the last tracked frames' made masks
        self.first_colours: list[float] = []  # of the first tracked frames' made masks
        self._probation: tuple[_Node, Observation] | None = None  # a keyframe waiting (`_probation_ends`)
        self.lost = False
        self.frames_lost = 0
        self._lost_because = ""  # why the loss under way began (the reason of its first frame)
        self._seen_past_run = 0  # frames in a row that saw past the model (_sees_past)
        self.sdf: InstrumentSDF | None = None  # the converged field the posture graph uses (L_SDF, eq. 11)
        self.fitter: BackgroundFitter | None = None
        self._field: InstrumentSDF | None = None  # the field refitted in line when there is no background fitter
        self._keyframes_added = 0  # by this tracker; sets the refit cadence (sdf.refit_every)
        self.model_points: np.ndarray | None = None  # the keyframes' points in the object frame
        self._model_fpfh: FpfhCloud | None = None  # model_points with their FPFH features, once a loss needs them
        self._model_span: float | None = None  # geometry.span of model_points, once a search needs it
        self._model_tree: cKDTree | None = None
        # per model point: frames that saw past it, frames that saw it or past it, whether a given mask made it
        self._past, self._views, self._given = np.zeros(0, int), np.zeros(0, int), np.zeros(0, bool)
        self._axis: tuple[np.ndarray, np.ndarray, float] | None = None  # long_axis of the first keyframe's points
        self.colour = ColourModel(self.cfg.preprocess.colour_bins, self.cfg.preprocess.colour_ring)
        self.model = model
        if model is not None:
            for kf in model.keyframes:
                self.pool.keyframes.append(kf)
                self._remember_points(kf)
            if model.sdf is not None and self.cfg.sdf.enabled:
                self._field = self.sdf = model.sdf
                self.fitter = BackgroundFitter(model.sdf, num_threads=1) if self.cfg.sdf.background else None

    # ----------------------------------------------------------------------------------------------- public API

    def register(self, frame: Frame, mask: np.ndarray) -> np.ndarray:
        """Start tracking on the first frame and its instrument mask; returns the first pose."""
        obs = preprocess(frame, mask, self.cfg.preprocess)
        self.colour.learn(frame.rgb, mask)
        if obs.n_valid < self.cfg.failure.min_pixels:
            raise ValueError(
                f"frame {frame.id}: only {obs.n_valid} instrument pixels with valid depth in the first mask "
                f"(need {self.cfg.failure.min_pixels})"
            )
        if self.model is not None:
            return self._register_to_model(obs)
        pts, _ = backproject(frame.depth, frame.K, mask)  # the whole masked cloud, not the filtered subset
        pose = make_T(np.eye(3), object_origin(pts))
        if self.cfg.sdf.enabled:
            self._field = new_field(self.cfg.sdf, obs, pose[:3, 3])
            self.fitter = (BackgroundFitter(self._field, self.cfg.sdf.refit_iterations, num_threads=1)
                           if self.cfg.sdf.background else None)
        node = self._node(obs, self.extractor(obs), pose)
        self.recent.append(node)
        self._add_keyframe(node, obs)
        return pose

    def first_result(self, pose: np.ndarray) -> TrackResult:
        """The first frame's result, its ``pose`` from `register`: tracked, with the directions its solve against a
        registered model left unmeasured (a turn about a round shaft is then the global registration's guess);
        without a model the first frame sets the object frame and nothing is left unmeasured."""
        return TrackResult(pose, TRACKED, 1.0, unmeasured=tuple(self.recent[-1].unmeasured))

    def _register_to_model(self, obs: Observation) -> np.ndarray:
        """First pose against a registered model: feature RANSAC with its keyframes, else FPFH registration of
        the masked cloud, refined by the posture graph; the object frame is the model's."""
        feats = self.extractor(obs)
        best = None
        for kf in self.pool.keyframes:
            pair = self._matches(kf, feats)
            if pair is not None and (best is None or len(pair[1]) > len(best[1][1])):
                best = (kf, pair)
        if best is not None:
            pose, edges = best[1][0] @ best[0].pose, [(best[0], *best[1][1:])]
        else:
            found = global_register(obs.points()[0], self._model_features(), seeds=[self.cfg.seed])
            if not found:
                raise ValueError(f"frame {obs.frame.id}: too few instrument points to find the model")
            pose, edges = self._slid_to_silhouette(found[0][0], obs), []
        node = self._node(obs, feats, orthonormalize(pose))
        node.pose = orthonormalize(self._optimise(node, edges, obs=obs))
        if self._confidence(node) < self.cfg.failure.min_global_overlap:
            raise ValueError(f"frame {obs.frame.id}: the model's instrument was not found inside the first mask")
        self.recent.append(node)
        return node.pose

    def _slid_to_silhouette(self, pose: np.ndarray, obs: Observation) -> np.ndarray:
        """``pose`` slid along the model's long axis, in ``failure.slide_step`` steps over the model's length either
        way, to where the model's silhouette agrees best with the frame's mask (`masking.silhouette_iou`; the least
        slide among equals). A frame that shows a bare stretch of shaft fits the model's points equally well
        anywhere along it, but at a wrong slide the model's tip or handle shows where the mask has none."""
        step = self.cfg.failure.slide_step
        if step <= 0:
            return pose
        _, axis, _ = long_axis(self.model_points)
        along = self.model_points @ axis
        n = int(np.ceil((along.max() - along.min()) / step))
        slides = sorted(np.arange(-n, n + 1) * step, key=abs)
        poses = [pose @ make_T(np.eye(3), d * axis) for d in slides]
        ious = [silhouette_iou(self.model_points, p, obs.K, obs.mask) for p in poses]
        return poses[int(np.argmax(ious))]

    def mesh(self) -> trimesh.Trimesh | None:
        """The reconstructed instrument (object frame, metres): the latest field, its box lengthened along the shaft
        to the keyframes' points (`shaft_range`), refitted on every keyframe, then marching cubes."""
        if not self.cfg.sdf.enabled or not self.pool.keyframes:
            return None
        psi = self._field
        if self.fitter is not None:
            self.fitter.close()
            if self.fitter.error is not None:
                raise self.fitter.error
            psi = self.fitter.latest() or psi
        psi = psi.lengthened(*shaft_range(psi, self.model_points))
        psi.refit(self.views())
        psi.forget_rays()  # every keyframe's (tens of MB); a later fit is a new start
        self._field = psi
        self._refine_keyframes(psi)
        mesh = self.surface(psi)
        return mesh if len(mesh.faces) else None

    def fitted_field(self) -> InstrumentSDF | None:
        """The newest fitted field: after `mesh()` the final one, fitted on every keyframe; before it, the newest
        background fit (waiting for the one in progress) or the field refitted in line; None when none was fitted."""
        psi = self._field
        if (psi is None or not psi.fitted) and self.fitter is not None:
            self.fitter.wait()
            psi = self.fitter.latest()
        return psi if psi is not None and psi.fitted else None

    def surface(self, psi: InstrumentSDF) -> trimesh.Trimesh:
        """Marching cubes of ``psi`` kept to what the keyframes saw: faces within ``sdf.mesh_seen`` voxels of the
        model points, pieces under ``sdf.mesh_floater`` of the largest's seen area dropped (`InstrumentSDF.mesh`)."""
        c = self.cfg.sdf
        return psi.mesh(keep_frac=c.mesh_floater, seen=self.model_points, seen_dist=c.mesh_seen * c.voxel_size)

    def observe(self, frame: Frame) -> Observed | None:
        """The frame preprocessed with its given mask, and its features: the part of `track` that depends on the
        frame alone, so that a caller can make the next frame's in another thread while this one is tracked (and
        pass it to `track`). None for a frame without a mask. Not thread-safe with itself: one caller thread."""
        if frame.mask is None:
            return None
        clock = _Clock()
        obs = preprocess(frame, frame.mask, self.cfg.preprocess, mask_given=True)
        clock.lap("preprocess")
        if obs.n_valid < self.cfg.failure.min_pixels:  # `track` loses it before looking for features
            return Observed(obs, None, clock.laps)
        if self._observer is None:
            self._observer = FeatureExtractor(self.cfg.ransac.features, self.cfg.ransac.max_keypoints)
        features = self._observer(obs)
        clock.lap("features")
        return Observed(obs, features, clock.laps)

    def track(self, frame: Frame, mask: np.ndarray | None = None, observed: Observed | None = None) -> TrackResult:
        """One tracking step (Stage 2): preprocess, coarse pose (eq. 5), posture graph (eqs. 7-11), memory (eq. 6).
        ``observed``: `observe(frame)`, made beforehand; ``mask`` is then the frame's mask."""
        if observed is not None and (observed.obs.frame is not frame or mask is not frame.mask):
            raise ValueError(f"frame {frame.id}: tracked with another frame's or mask's observation")
        clock = _Clock()
        if self.lost and mask is not None and not self._shows(frame, mask):
            return self._lose(clock, unseen(mask, self.cfg.failure.min_pixels))
        if self.lost and mask is None and not self._relocalisation_due():
            return self._lose(clock, NOT_TRIED)
        self._update_sdf()
        colour_model = self._colour()
        searched = mask is None and self.lost and colour_model is not None
        if searched:
            found = self._search(frame, colour_model, clock)
        else:
            found = self._located(frame, mask, clock, observed)
        if isinstance(found, str):
            return self._lose(clock, found)
        obs, node, inliers = found
        colour = self._mask_colour(obs)
        if searched and not self._looks_like_before(colour):
            return self._lose(clock, NO_POSE)
        pose = node.pose
        confidence = self._confidence(node)
        if confidence < self._least_confidence(pose):
            return self._lose(clock, UNSURE, confidence)
        if self._sees_past(obs, pose):
            return self._lose(clock, SEEN_PAST, confidence)
        status = RELOCALISED if self.lost else TRACKED
        if mask is None and status == TRACKED:
            self._learn_occluders(frame, pose)
            self._carve(frame, pose)
        self.lost = False
        self.frames_lost = 0
        self.recent.append(node)
        predicted_area = None if obs.mask_given else int(np.count_nonzero(obs.mask))
        if status == TRACKED and self._probation is not None:
            self._probation_ends(node, obs)
        if self.cfg.pool.enabled and self.pool.should_add(pose, predicted_area):
            if not self._unlike_first(colour):
                self._add_keyframe(node, obs)
            elif self._probation is None:  # one at a time
                self._probation = (node, obs)
        clock.lap("pool")
        if colour is not None and status == TRACKED:
            self.colours.append(colour)
            if len(self.first_colours) < COLOURS_KEPT:
                self.first_colours.append(colour)
        return TrackResult(pose, status, confidence, clock.laps, inliers, node.sdf,
                           unmeasured=tuple(node.unmeasured), colour=colour)

    # -------------------------------------------------------------------------------------------------- stages

    def _located(self, frame: Frame, mask: np.ndarray | None, clock: _Clock,
                 observed: Observed | None = None) -> tuple[Observation, _Node, int] | str:
        """The frame's observation (``observed``'s when given), its node at the tracked pose and the feature inlier
        count: coarse pose (eq. 5) and posture graph (eqs. 7-11) while tracking, re-localisation (step 5) while
        lost; why not when lost. Without a mask, one made at the last pose that holds too few trusted points is made
        again ``preprocess.predicted_mask_wide_margin`` pixels wide before the frame is lost (when that is wider)."""
        predicted = mask is None
        if predicted:
            mask = self._predicted_mask(frame, self.recent[-1].pose)
        if observed is None:
            obs = preprocess(frame, mask, self.cfg.preprocess, mask_given=not predicted)
        else:
            obs = observed.obs
            clock.add(observed.timings)  # made beforehand, in another thread
        clock.lap("preprocess")
        wide = self.cfg.preprocess.predicted_mask_wide_margin
        if predicted and obs.n_valid < self.cfg.failure.min_pixels and wide > self.cfg.preprocess.predicted_mask_margin:
            # the instrument moved further than the margin since the last pose (a fast hand): masked again wider
            mask = self._predicted_mask(frame, self.recent[-1].pose, wide)
            obs = preprocess(frame, mask, self.cfg.preprocess, mask_given=False)
            clock.lap("preprocess")
        if obs.n_valid < self.cfg.failure.min_pixels:
            return unseen(mask, self.cfg.failure.min_pixels)
        feats = self.extractor(obs) if observed is None else observed.features
        clock.lap("features")
        if self.lost:  # the candidates are refined by the posture graph as they compete
            found = self._relocalise(obs, feats)
            clock.lap("ransac")
            if found is None:
                return NO_POSE
            node, inliers = found
        else:
            coarse = self._coarse_pose(obs, feats)
            clock.lap("ransac")
            if coarse is None:
                return NO_POSE
            pose, edges, inliers = coarse
            node = self._node(obs, feats, orthonormalize(pose))  # chained estimates would drift off SO(3)
            if self.cfg.graph.enabled:
                node.pose = orthonormalize(self._optimise(node, edges, obs=obs))
                node = self._checked_jump(obs, feats, node)
                clock.lap("graph")
                if predicted and self.cfg.preprocess.predicted_mask_remask:
                    obs, node = self._remasked(obs, node, edges)
                    clock.lap("remask")
        return obs, node, inliers

    def _search(self, frame: Frame, colour: ColourModel, clock: _Clock) -> tuple[Observation, _Node, int] | str:
        """Re-localisation without a mask (step 5): against each of the ``failure.search_regions`` colour regions
        nearest the last position (`masking.search_regions`), none wider than ``failure.search_max_span`` times the
        model (a wall of its colour far behind, on which registration alone took seconds); the winner is the pose
        whose model silhouette agrees best with its region (`masking.silhouette_iou`), if by at least
        ``failure.relocalise_min_iou``. The model's fit alone prefers a fingertip-sized region, which some part of
        the model always fits. Regions are looked for within the reach without its cap: a region's centroid can lie
        far from the instrument's origin (a long shaft), and the pose found on it is held to the cap anyway. A region
        with too few trusted points is tried grown into the instrument's other colours around it
        (`masking.grow_region`). The winner is masked again at its pose (`track` then holds that mask to the colour
        before the loss, `_looks_like_before`). When lost: `HIDDEN` if no region had enough trusted points, else
        `NO_POSE`."""
        f, pre = self.cfg.failure, self.cfg.preprocess
        seen = max(max(k.area for k in self.pool.keyframes), f.min_pixels)
        posterior = colour.posterior(frame.rgb)
        wide = f.search_max_span * self._span() if f.search_max_span > 0 else np.inf
        regions = search_regions(posterior, frame.depth, frame.K, self._last_seen(),
                                 self._reach(frame.index, capped=False), pre.search_mask_colour,
                                 (f.min_pixels, 3 * seen), f.search_regions, max_span=wide)
        clock.lap("preprocess")
        best, best_iou, reason = None, f.relocalise_min_iou, HIDDEN
        for region in regions:
            obs = preprocess(frame, region, pre, mask_given=False)
            if obs.n_valid < f.min_pixels and pre.search_grow_colour > 0:
                region = grow_region(region, frame.depth, posterior, pre.search_grow_colour, pre.search_grow_reach,
                                     pre.predicted_mask_grow_step)
                obs = preprocess(frame, region, pre, mask_given=False)
            clock.lap("preprocess")
            if obs.n_valid < f.min_pixels:
                continue
            reason = NO_POSE
            feats = self.extractor(obs)
            clock.lap("features")
            found = self._relocalise(obs, feats)
            if found is not None:
                iou = silhouette_iou(self.model_points, found[0].pose, frame.K, region)
                if iou >= best_iou:
                    best, best_iou = (obs, *found), iou
            clock.lap("ransac")
        if best is None:
            return reason
        if self.cfg.preprocess.predicted_mask_remask:
            # the region may have merged with a hand of the instrument's colour: mask again at the found pose
            obs, node = self._remasked(best[0], best[1], [])
            best = (obs, node, best[2])
            clock.lap("remask")
        return best

    def _looks_like_before(self, colour: float | None) -> bool:
        """Whether the mask made at a re-localised pose, its ``colour`` (`_mask_colour`), scores at least
        ``failure.relocalise_colour`` of the colour that the last tracked frames' made masks scored, their median.
        A pose found on part of the instrument's colours but lying off it makes a mask of what lies around it, which
        looks less like the instrument than the masks before the loss did (benchmarks/RESULTS.md, "A
        re-localisation held to the colour before the loss"). A light that takes the instrument's colours away while
        it is lost refuses the right pose as well; it also hides the instrument from the colour search that finds
        its regions. ``failure.relocalise_colour`` 0 turns the check off."""
        share = self.cfg.failure.relocalise_colour
        if share <= 0 or colour is None or not self.colours:
            return True
        return colour >= share * float(np.median(self.colours))

    def _unlike_first(self, colour: float | None) -> bool:
        """Whether a made mask's colour (`_mask_colour`) is below ``pool.keyframe_colour`` of the median the first
        `COLOURS_KEPT` tracked frames' made masks scored: the mask has taken in something of another colour (a
        glove round the instrument) or shows a part of it the first frame did not (a handle in a new colour)."""
        share = self.cfg.pool.keyframe_colour
        if share <= 0 or colour is None or len(self.first_colours) < COLOURS_KEPT:
            return False
        return colour < share * float(np.median(self.first_colours))

    def _probation_ends(self, now: _Node, obs: Observation) -> None:
        """A keyframe on probation (`_unlike_first`) joins the pool when, ``pool.probation_frames`` or more frames
        later, this tracked frame sees its new points (more than `NEW_POINT_GAP` off the model) where they were: at
        least ``pool.probation_agree`` of those it sees at or past them lie at their depth (``graph.free_space_tol``).
        A part of the instrument stays where it was on the instrument; a hand that the mask took in moves on, and
        the frame sees past where it was. With fewer than `PROBATION_MIN_POINTS` new points it leaves (it adds next
        to nothing, and its pose came from a mask unlike the first ones); with fewer seen it waits, for at most
        three times ``pool.probation_frames``, then leaves (benchmarks/RESULTS.md, "A keyframe in new colours on
        probation")."""
        node, kobs = self._probation
        c, waited = self.cfg.pool, now.index - node.index
        if waited < c.probation_frames:
            return
        pts = transform(inv_T(node.pose), node.xyz[node.xyz[..., 2] > 0])
        gap, _ = self._model_tree.query(pts, distance_upper_bound=NEW_POINT_GAP)
        on, past = self._seen(pts[~np.isfinite(gap)], now.pose, obs.frame)
        at, seen = int(on.sum()), int(on.sum() + past.sum())
        few = len(on) < PROBATION_MIN_POINTS  # it adds next to nothing to the model
        if not few and seen < PROBATION_MIN_POINTS and waited < 3 * c.probation_frames:
            return
        self._probation = None
        if not few and seen >= PROBATION_MIN_POINTS and at >= c.probation_agree * seen:
            self._add_keyframe(node, kobs)

    def _last_seen(self) -> np.ndarray:
        """Where the instrument was last seen (camera frame): the median of the last tracked frame's grid points
        (those its graph solve used). Its object origin (the first frame's centroid) can lie a hand's width away
        along a shaft whose other end is what shows now."""
        last = self.recent[-1]
        pts = last.grid_points.p
        return np.median(pts, axis=0) if len(pts) else last.pose[:3, 3]

    def _colour(self) -> ColourModel | None:
        """The colour model, when a colour gate, the mask's growth or the lost search uses it."""
        pre = self.cfg.preprocess
        gates = (pre.predicted_mask_colour, pre.predicted_mask_colour_inside, pre.predicted_mask_grow)
        return self.colour if max(gates) > 0 else None

    def _mask_colour(self, obs: Observation) -> float | None:
        """The mean colour posterior (`ColourModel.posterior`, the first frame's colours against its surroundings')
        of the pixels of a mask the tracker made; None for a given mask. A made mask that has taken in a hand or
        tissue looks less like the instrument; so do parts of it in colours the first frame did not show."""
        mask = obs.mask[obs.box]  # the mask lies in the crop: selecting there, not over the image, is the cost
        if obs.mask_given or self.colour.instrument is None or not mask.any():
            return None
        return float(np.mean(self.colour.posterior(obs.frame.rgb[obs.box][mask])))

    def _node(self, obs: Observation, feats: Features, pose: np.ndarray) -> _Node:
        factor = max(1, round(self.cfg.graph.depth_downscale * obs.shape[1] / 640))
        xyz, nrm, K = obs.grid(factor)
        return _Node(obs.frame.id, obs.frame.index, pose, feats, xyz, nrm, K)

    def _matches(self, ref: _Node | Keyframe, feats: Features,
                 pose: np.ndarray | None = None) -> tuple[np.ndarray | None, np.ndarray, np.ndarray] | None:
        """Feature correspondences with a reference frame as (T_ref_to_cur, ref points, current points): RANSAC
        inliers (eq. 5), or, when RANSAC finds none and a pose estimate is given, the matches that agree with it
        (within twice the RANSAC threshold; T is then None)."""
        ia, ib = match(ref.features, feats, self.extractor.norm, self.cfg.ransac.ratio_test)
        if len(ia) < self.cfg.ransac.min_inliers:
            return None
        src, dst = ref.features.subset(ia), feats.subset(ib)
        res = ransac_pose(src.xyz, dst.xyz, self.cfg.ransac, self.rng, src.normals, dst.normals)
        if res.T is not None:
            return res.T, src.xyz[res.inliers], dst.xyz[res.inliers]
        if pose is None:
            return None
        pred = transform(pose @ inv_T(ref.pose), src.xyz)
        ok = np.linalg.norm(pred - dst.xyz, axis=1) < 2 * self.cfg.ransac.inlier_dist
        return (None, src.xyz[ok], dst.xyz[ok]) if ok.sum() >= self.cfg.ransac.min_inliers else None

    def _coarse_pose(self, obs: Observation, feats: Features) -> tuple[np.ndarray, list[tuple], int] | None:
        """Coarse pose (eq. 5) from the last tracked frame, else from the memory pool; with too little texture, the
        prediction for the graph's geometry to align."""
        last = self.recent[-1]
        refs = [last] + [k for k in self.pool.select(last.pose, 3) if k.frame_id != last.frame_id]
        for ref in refs:
            pair = self._matches(ref, feats)
            if pair is None:
                continue
            T, p_ref, p_cur = pair
            pose = T @ ref.pose
            if self._plausible(pose):
                return pose, [(ref, p_ref, p_cur)], len(p_ref)
        if not self.cfg.graph.enabled:
            return None
        # Too little texture for features: predict (constant velocity) and let the graph's geometry (L_2D) and the
        # matches that agree with the prediction align it.
        pose = self._predicted_pose()
        pair = self._matches(last, feats, pose)
        return pose, [] if pair is None else [(last, *pair[1:])], 0

    def _checked_jump(self, obs: Observation, feats: Features, node: _Node) -> _Node:
        """The tracked ``node``, or the constant-velocity prediction refined by the posture graph (eqs. 7-11) when
        the node departs from it by more than ``ransac.check_jump_trans`` or ``ransac.check_jump_rot_deg`` and the
        model fits the prediction better (`_fit_error` at most ``ransac.check_jump_fit`` times the node's). A few
        feature matches between a shaft's repeated markings move the pose along the shaft by their spacing; the
        shaft's geometry does not hold it there (its points slide along themselves), but its end no longer meets the
        model's."""
        r = self.cfg.ransac
        if r.check_jump_fit <= 0:
            return node
        predicted = self._predicted_pose()
        if within(inv_T(predicted) @ node.pose, r.check_jump_trans, r.check_jump_rot_deg):
            return node
        drawn = self.rng.bit_generator.state  # kept, the node leaves the run's random draws as they were
        steady = self._node(obs, feats, predicted)
        steady.pose = orthonormalize(self._optimise(steady, [], obs=obs))
        if self._fit_error(self._model_distances(steady)) <= r.check_jump_fit * self._fit_error(
                self._model_distances(node)):
            return steady
        self.rng.bit_generator.state = drawn
        return node

    def _candidates(self, obs: Observation, feats: Features,
                    last: np.ndarray) -> list[tuple[np.ndarray, list[tuple], int]]:
        """Candidate poses after a loss: feature RANSAC (eq. 5) against the keyframes (those that saw the last
        view first), ICP against the model from the last pose, and FPFH registration against the model with a few
        seeds."""
        cands: list[tuple[np.ndarray, list[tuple], int]] = []
        near = self.pool.select(last, len(self.pool))
        for kf in near + [k for k in self.pool.keyframes if k not in near]:
            pair = self._matches(kf, feats)
            if pair is not None:
                cands.append((pair[0] @ kf.pose, [(kf, *pair[1:])], len(pair[1])))
                if len(cands) == self.cfg.failure.relocalise_candidates:
                    break
        if self.model_points is not None:
            points = obs.points()[0]
            cands.append((icp_from(points, self.model_points, last), [], 0))
            seeds = range(self.cfg.seed, self.cfg.seed + self.cfg.failure.relocalise_candidates)
            for pose, explained in global_register(points, self._model_features(), seeds=seeds):
                if explained >= self.cfg.failure.min_global_overlap:
                    cands.append((pose, [], 0))
        return cands

    def _best_candidate(self, obs: Observation, feats: Features, cands: list[tuple[np.ndarray, list[tuple], int]],
                        last: np.ndarray) -> tuple[_Node, int] | None:
        """Refine each candidate (`_refined`) and keep the one the model fits best (`_fit_error`); among equally
        good fits, the one whose appearance agrees best with the keyframes (`_appearance`), then the least motion
        from ``last``. A candidate whose appearance disagrees (NCC below ``failure.relocalise_min_ncc``: the
        geometry fits, the markings do not, as for a round shaft turned end for end) is dropped. Returns the
        winner's node, at its refined pose, and its feature inlier count; without the graph, the first candidate
        as it came."""
        if not self.cfg.graph.enabled:
            return (self._node(obs, feats, orthonormalize(cands[0][0])), cands[0][2]) if cands else None
        refined = [(c, inliers) for pose, edges, inliers in cands
                   if (c := self._refined(obs, feats, pose, edges, last)) is not None]
        if not refined:
            return None
        # The candidates share the frame's points (camera frame); their intensities are read once.
        xyz = refined[0][0].node.xyz
        points = xyz[xyz[..., 2] > 0]
        values, _ = sample(intensity(obs.frame.rgb), project(points, obs.K)[0])
        kept = []
        for c, inliers in refined:
            c = c._replace(looks=self._appearance(c.node.pose, points, values))
            if c.looks is None or c.looks >= self.cfg.failure.relocalise_min_ncc:
                kept.append((c, inliers))
        if not kept:
            return None
        best = min(c.fit for c, _ in kept)
        tied = [k for k in kept if k[0].fit <= 1.2 * best + 5e-4]
        c, inliers = min(tied, key=lambda k: (-(k[0].looks if k[0].looks is not None else -1.0), k[0].move))
        return c.node, inliers

    def _refined(self, obs: Observation, feats: Features, pose: np.ndarray, edges: list[tuple],
                 last: np.ndarray) -> _Candidate | None:
        """A re-localisation candidate refined by the posture graph, its motion prior at the candidate itself along
        the directions the frame leaves free (a slide along a shaft, a turn about it stay where the candidate put
        them; a prior at ``last`` would pull them back to where the instrument was before the loss), its appearance
        not yet scored; the candidate as found when the graph leaves the frame's median point further from the model
        (L_FS, the frames before the loss and the memory keyframes can each pull a true pose off it, as on a bottle
        nearly hidden in the hand that holds it). None when its origin moved further than the physical bound allows
        over the frames since ``last`` (a look-alike elsewhere in the image), or when its median point lies further than
        ``failure.relocalise_max_fit`` from the model (median: parts of the instrument the model has not seen yet do
        not count against it): a wrong pose taken here would be tracked on, and its keyframes would spoil the
        model."""
        node = self._node(obs, feats, orthonormalize(pose))
        found = self._model_distances(node)
        start, cached = node.pose, node.distances
        node.pose = orthonormalize(self._optimise(node, list(edges), candidate=True, obs=obs))
        dist = self._model_distances(node)
        if np.median(found) < np.median(dist):  # the graph pulled it off the model: the node as it was found
            node.pose, node.distances, node.sdf, dist = start, cached, False, found
        motion = inv_T(last) @ node.pose
        if np.linalg.norm(motion[:3, 3]) > self._reach(obs.frame.index):
            return None
        if not np.median(dist) <= self.cfg.failure.relocalise_max_fit:  # the model does not lie on the frame
            return None
        move = np.linalg.norm(motion[:3, 3]) + 0.1 * np.radians(rotation_angle_deg(motion[:3, :3]))
        return _Candidate(node, self._fit_error(dist), None, move)

    def _relocalise(self, obs: Observation, feats: Features) -> tuple[_Node, int] | None:
        """Re-localisation after a loss (step 5) against the memory pool and the model; shortly after the loss the
        last pose competes too, unless the loss began with the camera seeing through the model there (`SEEN_PAST`):
        taken again, that pose would be lost again by the same check a few frames later, over and over."""
        last = self.recent[-1].pose
        cands = self._candidates(obs, feats, last)
        if (self.cfg.graph.enabled and self.frames_lost <= self.cfg.failure.relocalise_window
                and self._lost_because != SEEN_PAST):  # not a pose the camera was seeing through
            cands.append((last, [], 0))
        return self._best_candidate(obs, feats, cands, last)

    def _model_features(self) -> FpfhCloud:
        """The model's FPFH features for `global_register`, computed once after each change of the model
        (`_set_model_points`): a loss tries several regions a frame against the same model."""
        if self._model_fpfh is None:
            self._model_fpfh = FpfhCloud.of(self.model_points)
        return self._model_fpfh

    def _span(self) -> float:
        """The model's `geometry.span`, found once after each change of the model: a long loss searches every few
        frames against the same model."""
        if self._model_span is None:
            self._model_span = span(self.model_points)
        return self._model_span

    def _relocalisation_due(self) -> bool:
        """Whether to try re-localising this lost frame, which came without a mask (step 5): every frame of the
        first ``relocalise_window`` after the loss, then every ``relocalise_every``-th. The search is the costliest
        step, and an instrument that has stayed away that long is found at most ``relocalise_every`` - 1 frames
        later. A frame that comes with its mask is tried whenever the mask shows the instrument (`_shows`)."""
        late = self.frames_lost - self.cfg.failure.relocalise_window
        return late <= 0 or late % max(self.cfg.failure.relocalise_every, 1) == 0

    def _shows(self, frame: Frame, mask: np.ndarray) -> bool:
        """Whether a given mask shows the instrument: ``failure.min_pixels`` of it with depth (a cheap bound on the
        trusted pixels preprocessing keeps)."""
        return np.count_nonzero(mask & (frame.depth > 0)) >= self.cfg.failure.min_pixels

    def _reach(self, index: int, capped: bool = True) -> float:
        """How far (m) the instrument's origin can have moved since the last tracked frame, by frame ``index``:
        ``failure.relocalise_max_speed`` times the frames between, at most ``failure.relocalise_max_reach`` unless
        not ``capped`` (a look-alike elsewhere in the scene is what a long loss would otherwise let in)."""
        f = self.cfg.failure
        reach = f.relocalise_max_speed * (index - self.recent[-1].index)
        return min(reach, f.relocalise_max_reach) if capped and f.relocalise_max_reach > 0 else reach

    def _predicted_pose(self) -> np.ndarray:
        """Constant-velocity prediction from the last two tracked frames when they are consecutive (a gap, such
        as a loss, gives no velocity), else the last pose."""
        if len(self.recent) < 2 or self.lost or self.recent[-1].index - self.recent[-2].index != 1:
            return self.recent[-1].pose
        a, b = self.recent[-2].pose, self.recent[-1].pose
        pred = b @ inv_T(a) @ b
        return pred if self._plausible(pred) else b

    def _plausible(self, pose: np.ndarray) -> bool:
        """Whether the motion from the last tracked pose to ``pose`` is within the physical bounds (step 5):
        rotation of the instrument and displacement of its origin between consecutive frames."""
        return plausible(inv_T(self.recent[-1].pose) @ pose, self.cfg.ransac)

    def _optimise(self, node: _Node, edges: list, candidate: bool = False,
                  obs: Observation | None = None) -> np.ndarray:
        """Posture graph over the current frame, adjacent frames and K memory frames (eqs. 7-11); as in the paper
        (eq. 8) only the current pose xi_t is optimised, the other nodes are held fixed. The motion prior holds
        what the data leave free at the node's starting (coarse) pose, along the directions ``graph.prior_null``
        selects, with weight ``graph.w_m``; for a re-localisation ``candidate``, ``failure.relocalise_prior_null``
        and ``failure.relocalise_w_m``. With ``obs`` and ``graph.w_fs`` set, L_FS keeps the model out of what the
        frame saw past (`_free_space`). A frame that came with its mask, unless it is a re-localisation
        ``candidate`` (held where it was found), also gets L_CV (`_coverage`): its points kept out of what the first
        keyframe saw past. A frame that came with its mask takes ``graph.given_mask_iterations``
        Gauss-Newton steps, one on a predicted mask ``graph.iterations``: its mask is found again at the pose they
        reach (`_remasked`), which fewer steps leave short. Sets
        ``node.sdf`` to whether L_SDF was in the graph (a field that agrees with the frame, `_field_agrees`, and
        ``graph.w_s`` > 0), and ``node.unmeasured`` to the directions its data left free (`Unmeasured`)."""
        others: list[_Node | Keyframe] = [e[0] for e in edges]
        prior = node.pose.copy()
        for prev in reversed(self.recent):
            if prev not in others:
                others.append(prev)
        if self.cfg.pool.enabled:
            seen = {o.frame_id for o in others}
            for kf in self.pool.select(node.pose, self.cfg.pool.K, exclude=seen):
                pair = self._matches(kf, node.features, node.pose)
                others.append(kf)
                if pair is not None:
                    edges.append((kf, *pair[1:]))
        nodes = [node.graph_node(fixed=False)]
        nodes += [GraphNode(o.pose, o.xyz, o.normals, o.K_grid, True, o.grid_points) for o in others]
        index = {id(o): i + 1 for i, o in enumerate(others)}
        graph_edges = [FeatureEdge(0, index[id(ref)], p_cur, p_ref) for ref, p_ref, p_cur in edges]
        use_sdf = self.sdf is not None and self.cfg.graph.w_s > 0 and self._field_agrees(node)
        pairs = [p for j in range(1, len(nodes)) for p in ((0, j), (j, 0))]  # the other poses are fixed
        cfg = self.cfg.graph
        if obs is not None and obs.mask_given:
            cfg = replace(cfg, iterations=cfg.given_mask_iterations)
        if candidate:
            cfg = replace(cfg, prior_null=self.cfg.failure.relocalise_prior_null, w_m=self.cfg.failure.relocalise_w_m)
        free_space = None
        if obs is not None and cfg.w_fs > 0 and self.model_points is not None:
            free_space = self._free_space(node, obs, cfg)
        unmeasured: dict[int, list[Unmeasured]] = {}
        poses = optimize_graph(nodes, graph_edges, cfg, self.sdf if use_sdf else None,
                               [0] if use_sdf else [], pairs_2d=pairs, priors=[(0, prior)], free_space=free_space,
                               coverage=None if candidate else self._coverage(node, obs, cfg), unmeasured=unmeasured)
        node.sdf, node.unmeasured = use_sdf, unmeasured.get(0, [])
        return poses[0]

    def _free_space(self, node: _Node, obs: Observation, cfg: GraphConfig) -> tuple[int, FreeSpace] | None:
        """L_FS (`posture_graph.FreeSpace`) for the node: on a frame that came with its mask (or any, with
        ``graph.free_space_predicted``) every model point against the mask; on one without, with
        ``graph.free_space_background`` > 0, the points that given masks made (the first frame's, when only it had
        one) against the background, the pixels whose depth lies that much or more behind the model's furthest
        point at the node's pose. A mask predicted from the model (or a colour region while lost) leaves out what
        the model's pose leaves out, so the pixels beside it are not known to be free; the background is. The
        points predicted masks added can hold fingers a pose put on the instrument, which the background would then
        push the pose off."""
        if obs.mask_given or cfg.free_space_predicted:
            points, edge = self.model_points, obs.mask_edge
        elif cfg.free_space_background > 0 and self._given.any():
            points = self.model_points[self._given]
            d = obs.frame.depth
            far = float((self.model_points @ node.pose[2, :3]).max()) + node.pose[2, 3]  # the model's furthest z
            near = d < far + cfg.free_space_background
            edge = MaskEdge.of(obs.mask | ((d > 0) & near))
        else:
            return None
        return 0, FreeSpace.of(points, edge, obs.frame.depth, obs.K, cfg.free_space_points)

    def _coverage(self, node: _Node, obs: Observation | None, cfg: GraphConfig) -> tuple | None:
        """L_CV (`posture_graph.Coverage`) for a frame that came with its mask, or any with
        ``graph.coverage_predicted``: its points against what the first keyframe saw past, the one keyframe whose
        mask always came with its frame and whose pose anchors the object frame (later keyframes carry the slides of
        their own poses: looking into them too broke bronchoscope_2 and thoracoscope_2). None on a frame with fewer
        than ``graph.coverage_min_share`` of the first keyframe's points (0 by default): an object mostly hidden in
        the hand that holds it leaves the pose loose, and a few of its points in the keyframe's free space can pull
        it further off."""
        if obs is None or not (obs.mask_given or cfg.coverage_predicted) or cfg.w_cv <= 0 or not self.pool.keyframes:
            return None
        first, points = self.pool.keyframes[0], node.grid_points.p
        if len(points) < cfg.coverage_min_share * len(first.grid_points.p):
            return None
        return 0, Coverage.of(points, first.view, inv_T(first.pose), cfg.coverage_points)

    def _field_agrees(self, node: _Node) -> bool:
        """Whether the field fits the frame at its coarse pose well enough to join the graph (L_SDF, eq. 11): the
        median |Psi| of the frame's points within its box below ``sdf.agree_tol`` (0: always). A field fitted from
        drifted keyframes otherwise pulls every later pose towards its own error."""
        tol = self.cfg.sdf.agree_tol
        if tol <= 0:
            return True
        pts = node.xyz[node.xyz[..., 2] > 0]
        if len(pts) == 0:
            return False
        psi, _ = self.sdf(transform(inv_T(node.pose), pts[:: max(1, len(pts) // 500)]))
        psi = psi[np.isfinite(psi)]  # points beyond the field's box
        return len(psi) > 0 and float(np.median(np.abs(psi))) < tol

    def _model_distances(self, node: _Node) -> np.ndarray:
        """Distance of each of the frame's points, in the object frame, to the model built so far (inf beyond
        assoc_dist); kept on the node for its pose and this model (the jump check and the confidence ask twice)."""
        if (node.distances is not None and node.distances[0] == node.pose.tobytes()
                and node.distances[1] is self._model_tree):
            return node.distances[2]
        pts = node.xyz[node.xyz[..., 2] > 0]
        if len(pts) == 0 or self._model_tree is None:
            return np.full(1, np.inf)
        dist, _ = self._model_tree.query(transform(inv_T(node.pose), pts),
                                         distance_upper_bound=self.cfg.graph.assoc_dist)
        node.distances = (node.pose.tobytes(), self._model_tree, dist)
        return dist

    def _appearance(self, pose: np.ndarray, points: np.ndarray, values: np.ndarray) -> float | None:
        """Best intensity NCC (`appearance.keyframe_ncc`) of the frame's instrument ``points`` (camera frame) and
        their intensities ``values``, at object pose ``pose``, with the three keyframes nearest in viewing
        direction; None when none of them sees enough of them."""
        f = self.cfg.failure
        scores = [keyframe_ncc(points, values, pose, kf, f.appearance_depth_tol, f.appearance_min_points)
                  for kf in self.pool.select(pose, 3, within_deg=180.0)]
        scores = [s for s in scores if s is not None]
        return max(scores) if scores else None

    def _fit_error(self, dist: np.ndarray) -> float:
        """Mean of `_model_distances` (m), each capped at assoc_dist."""
        return float(np.mean(np.minimum(dist, self.cfg.graph.assoc_dist)))

    def _least_confidence(self, pose: np.ndarray) -> float:
        """The confidence a pose needs: ``failure.min_confidence``; ``failure.moved_min_confidence`` where tracking
        (not re-localising) puts it beyond ``ransac.check_jump_trans`` or ``check_jump_rot_deg`` from the last
        tracked pose. Where little of the instrument shows, the graph can carry the pose off along what that part
        leaves free, frame after frame; a part coming into view, which the model lacks, comes at the instrument's
        pace. While the model is the first keyframe's view alone (a first mask of part of the instrument leaves
        much of the next frames new), the lower bound holds."""
        f, r = self.cfg.failure, self.cfg.ransac
        if (self.lost or len(self.pool.keyframes) < 2
                or within(inv_T(self.recent[-1].pose) @ pose, r.check_jump_trans, r.check_jump_rot_deg)):
            return f.min_confidence
        return max(f.min_confidence, f.moved_min_confidence)

    def _confidence(self, node: _Node) -> float:
        """Fraction of the frame's points within assoc_dist of the model."""
        return float(np.mean(np.isfinite(self._model_distances(node))))

    def _add_keyframe(self, node: _Node, obs: Observation) -> None:
        kf = Keyframe(node.frame_id, node.pose, node.features, node.xyz, node.normals, node.K_grid,
                      obs.frame.depth, obs.mask, obs.K, image=intensity(obs.frame.rgb))
        kf.grid_points = node.grid_points  # the same grid: its points were found once, for the frame
        self.pool.add(kf)
        self._remember_points(kf, obs.mask_given)
        self._keyframes_added += 1
        if (self._keyframes_added - 1) % self.cfg.sdf.refit_every:  # counted, not len(pool): a full pool stays full
            return
        views = self.views(self.cfg.sdf.max_views)
        if self.fitter is not None:
            if len(views) >= self.cfg.sdf.min_first_views:
                self.fitter.submit(views)
        elif self._field is not None:
            self._field.refit(views, self.cfg.sdf.refit_iterations)

    def _remember_points(self, kf: Keyframe, given: bool = True) -> None:
        pts = transform(inv_T(kf.pose), kf.xyz[kf.xyz[..., 2] > 0])
        if self._axis is None:
            self._axis = long_axis(pts)
        if self.model_points is not None:
            pts = np.concatenate([self.model_points, pts])
        self._set_model_points(voxel_downsample(pts, 0.002))  # the points kept come first, in their order
        new = len(self.model_points) - len(self._past)
        self._past = np.concatenate([self._past, np.zeros(new, int)])
        self._views = np.concatenate([self._views, np.zeros(new, int)])
        self._given = np.concatenate([self._given, np.full(new, given)])

    def _set_model_points(self, points: np.ndarray) -> None:
        """The model's points, and what is derived from them: a k-d tree now, FPFH features and span when a loss needs
        them."""
        self.model_points = points
        self._model_tree = cKDTree(points)
        self._model_fpfh = self._model_span = None

    def _carve(self, frame: Frame, pose: np.ndarray) -> None:
        """Free-space carving of the model, as TSDF fusion clears what has moved away: a point that a tracked frame
        sees more than ``graph.free_space_tol`` past, on more than ``pool.carve_ratio`` of the frames that saw it
        or past it (at least ``pool.carve_min_views``), was not the instrument (a hand that a predicted mask took
        in) and leaves the model. Points from given masks stay; a point hidden behind something counts for nothing."""
        c = self.cfg.pool
        if c.carve_ratio <= 0 or self.model_points is None:
            return
        on, past = self._seen(self.model_points, pose, frame)
        self._past += past
        self._views += past | on
        drop = ~self._given & (self._views >= c.carve_min_views) & (self._past > c.carve_ratio * self._views)
        if drop.any():
            keep = ~drop
            self._set_model_points(self.model_points[keep])
            self._past, self._views, self._given = self._past[keep], self._views[keep], self._given[keep]

    def _seen(self, points: np.ndarray, pose: np.ndarray, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """Per object-frame point at ``pose``: whether ``frame`` sees it at its depth (within
        ``graph.free_space_tol``) and whether it sees more than that past it. Neither where nothing was seen or
        something lies in front (hidden)."""
        uv, z = project(transform(pose, points), frame.K)
        d, inside = sample(frame.depth, uv)
        d = np.where(inside & (z > 1e-3), d, 0)  # 0: nothing seen
        tol = self.cfg.graph.free_space_tol
        return (d > 0) & (np.abs(d - z) <= tol), d > z + tol

    def views(self, n: int | None = None) -> list[View]:
        """The keyframes as SDF views at their tracked poses (the bound of a joint refinement holds against these);
        with ``n``, at most n of them spread evenly over the pool, the first keyframe always among them."""
        kfs = self.pool.keyframes
        if n is not None and len(kfs) > n:
            kfs = [kfs[i] for i in np.linspace(0, len(kfs) - 1, n).round().astype(int)]
        return [View(k.depth, k.mask, k.K, k.tracked_pose, k.frame_id) for k in kfs]

    def _update_sdf(self) -> None:
        """Swap in the newest converged field and the keyframe poses refined with it; never waits for a fit."""
        psi = self.fitter.latest() if self.fitter is not None else self._field
        if psi is not None and psi.converged and len(self.pool) >= self.cfg.sdf.min_keyframes:
            if psi is not self.sdf:
                self._refine_keyframes(psi)
            self.sdf = psi

    def _refine_keyframes(self, psi: InstrumentSDF) -> None:
        """Keyframe poses from a field fitted jointly with them (``sdf.refine_poses``); the first stays fixed."""
        for kf in self.pool.keyframes[1:]:
            pose = psi.refined_poses.get(kf.frame_id)
            if pose is not None:
                kf.pose = pose

    def _remasked(self, obs: Observation, node: _Node, edges: list) -> tuple[Observation, _Node]:
        """A frame that came without a mask, masked again at its tracked pose and its graph optimised once more
        (eqs. 7-11, the same feature edges): the mask predicted before tracking carries the prediction's error,
        and parts of the instrument it left out pull the pose towards the prediction. In the same crop the frame's
        depth filtering and keypoints are not done again (`preprocess.remasked`, `FeatureExtractor`)."""
        again = remasked(obs, self._predicted_mask(obs.frame, node.pose), self.cfg.preprocess)
        if again.n_valid < self.cfg.failure.min_pixels:
            return obs, node
        second = self._node(again, self.extractor(again), node.pose)
        second.pose = orthonormalize(self._optimise(second, edges, obs=again))
        return again, second

    def _learn_occluders(self, frame: Frame, pose: np.ndarray) -> None:
        """Teach the colour model what covers the instrument: the pixels inside the model's silhouette at the
        tracked ``pose`` that lie ``preprocess.colour_occluder_gap`` or more in front of it (a hand, a tool)."""
        gap = self.cfg.preprocess.colour_occluder_gap
        if gap <= 0 or self._colour() is None or self.model_points is None:
            return
        box, model = render_box(self.model_points, pose, frame.K, frame.depth.shape)
        depth = frame.depth[box]
        self.colour.add_surroundings(frame.rgb[box], (model > 0) & (depth > 0) & (depth < model - gap))

    def _predicted_mask(self, frame: Frame, pose: np.ndarray, margin: int | None = None) -> np.ndarray:
        """No mask given: render the keyframes' points at ``pose`` and keep depth-consistent pixels within ``margin``
        pixels of the rendering (``preprocess.predicted_mask_margin`` unless given)."""
        if self.model_points is None:
            return np.zeros(frame.depth.shape, bool)
        pre = self.cfg.preprocess
        margin = pre.predicted_mask_margin if margin is None else margin
        mask = predict_mask(self.model_points, pose, frame.K, frame.depth, margin,
                            pre.predicted_mask_tol, frame.rgb, self._colour(), pre.predicted_mask_colour,
                            pre.predicted_mask_front_tol, inside_posterior=pre.predicted_mask_colour_inside,
                            grow_posterior=pre.predicted_mask_grow, grow_step=pre.predicted_mask_grow_step,
                            grow_ratio=pre.predicted_mask_grow_ratio)
        if pre.predicted_mask_across > 0 and self._axis is not None:
            mask = within_reach(mask, frame.depth, frame.K, pose, self._axis, pre.predicted_mask_across)
        return mask

    def _sees_past(self, obs: Observation, pose: np.ndarray) -> bool:
        """True when the frame has seen past more than ``failure.max_seen_past`` of the model's silhouette at
        ``pose`` (`masking.seen_past`) on ``failure.seen_past_frames`` frames in a row: the pose is on something
        else. Frames that came with their mask are checked only with ``failure.seen_past_given``."""
        f = self.cfg.failure
        checked = f.max_seen_past < 1.0 and self.model_points is not None and (f.seen_past_given or not obs.mask_given)
        seen = checked and seen_past(self.model_points, pose, obs.K, obs.frame.depth,
                                     self.cfg.graph.free_space_tol) > f.max_seen_past
        self._seen_past_run = self._seen_past_run + 1 if seen else 0
        return self._seen_past_run >= f.seen_past_frames

    def _lose(self, clock: _Clock, reason: str, confidence: float = 0.0) -> TrackResult:
        if not self.lost:
            self._lost_because = reason
        self.lost = True
        self.frames_lost += 1
        self._seen_past_run = 0  # a lost frame ends the row
        clock.lap("pool")
        return TrackResult(None, LOST, confidence, clock.laps, reason=reason)

