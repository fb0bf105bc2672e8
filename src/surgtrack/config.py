"""One typed configuration for the whole method; names follow the paper's symbols (DESIGN.md section 3)."""

from __future__ import annotations

from dataclasses import MISSING, asdict, dataclass, field, fields


@dataclass
class PreprocessConfig:
    """Frame preprocessing (Stage 2, step 1)."""

    bilateral_d: int = 5  # bilateral filter diameter, pixels (0 disables)
    bilateral_sigma_depth: float = 0.01  # m
    bilateral_sigma_space: float = 3.0  # pixels
    mask_erosion: int = 1  # pixels eroded from the instrument mask before lifting points
    predicted_mask_margin: int = 4  # pixels a predicted mask (no mask given) extends beyond the rendered model
    predicted_mask_wide_margin: int = 12  # pixels, that mask made again when it held too few points (0: not)
    predicted_mask_tol: float = 0.01  # m a predicted mask's depth may lie outside the model's depth nearby
    predicted_mask_front_tol: float = 0.004  # m in front of the model, unless that loses a fifth of the mask
    predicted_mask_colour: float = 0.1  # min colour posterior of pixels beyond the rendered model (0: off)
    predicted_mask_colour_inside: float = 0.1  # min colour posterior of pixels inside the rendered model (0: off)
    colour_bins: int = 32  # colour model: histogram bins per RGB channel
    colour_ring: int = 120  # colour model: outer radius (pixels) of the first frame's surroundings around the mask
    colour_occluder_gap: float = 0.0  # m: pixels this far in front of the model at a tracked pose (no mask given)
    # are an occluder, and its colours join the colour model's surroundings (0: off; 0.02 measured, see RESULTS.md)
    predicted_mask_grow: float = 0.0  # min colour posterior of pixels a predicted mask grows into, connected to it
    # without a depth jump: parts of the instrument the model has not seen yet (0: off)
    predicted_mask_grow_step: float = 0.01  # m: depth jump between neighbours that stops the growth (of a predicted
    # mask, and of a search region short of points, search_grow_colour)
    predicted_mask_grow_ratio: float = 2.0  # growth beyond this times the mask's area is not taken
    predicted_mask_across: float = 0.0  # m beyond the first mask's reach across the instrument's long axis that a
    # predicted mask may extend (a hand beside the shaft stays out; 0: off)
    predicted_mask_remask: bool = True  # mask a frame again at its tracked pose and optimise the graph once more
    search_mask_colour: float = 0.6  # lost without a given mask: pixels whose colour is instrument with this posterior
    search_grow_colour: float = 0.4  # lost without a given mask: a colour region with too few trusted pixels grows
    # into pixels of at least this posterior within search_grow_reach of it (`masking.grow_region`; 0: off)
    search_grow_reach: int = 15  # pixels around such a region that it may grow into
    normal_step: int = 1  # normals from neighbours this many pixels away (larger: smoother, fewer thin-part pixels)
    max_grazing_deg: float = 80.0  # drop points whose normal is further than this from the viewing ray
    min_depth: float = 0.1  # m
    max_depth: float = 2.0  # m


@dataclass
class RansacConfig:
    """Coarse pose by RANSAC over 3-point rigid hypotheses (paper eq. 5)."""

    features: str = "sift"  # sift | orb | xfeat
    max_keypoints: int = 800
    ratio_test: float = 0.8  # Lowe ratio for descriptor matching
    hypotheses: int = 2000  # random 3-point samples; every triple instead when there are no more than this
    inlier_dist: float = 0.01  # m
    inlier_normal_deg: float = 20.0
    min_inliers: int = 5
    min_sample_spread: float = 0.002  # m; a 3-point sample whose triangle height is below this is degenerate
    refits: int = 2  # Kabsch refits on the inlier set after the best hypothesis
    max_jump_trans: float = 0.1  # m the instrument's origin moves between consecutive frames: beyond is implausible
    max_jump_rot_deg: float = 30.0  # degrees the instrument turns between consecutive frames (900 deg/s at 30 fps)
    check_jump_trans: float = 0.02  # m a tracked pose may depart from the constant-velocity prediction unchecked
    check_jump_rot_deg: float = 10.0  # degrees, likewise; beyond either, the refined prediction competes
    check_jump_fit: float = 0.8  # the prediction wins when the model fits it at most this times as far (0: off)


@dataclass
class PoolConfig:
    """Posture memory pool P = {(xi_i, M_i)} (paper eq. 6)."""

    enabled: bool = True  # False: the graph uses adjacent frames only (ablation "w/o posture memory pool")
    keyframe_rot_deg: float = 5.0  # add a keyframe when its rotation differs by >= this from every keyframe
    max_size: int = 60  # cap; retention keeps view coverage
    K: int = 9  # memory frames selected as graph nodes
    overlap_normal_deg: float = 70.0  # view overlap: normals facing the camera within this angle
    min_predicted_area: float = 0.25  # a predicted mask joins the pool only with this fraction of its largest mask
    carve_ratio: float = 0.0  # a model point seen past on more than this share of the frames that saw it leaves
    carve_min_views: int = 5  # ... once that many frames saw it (0 ratio: never; only frames without a given mask)
    keyframe_colour: float = 0.85  # a keyframe whose made mask's colour is below this of the first tracked frames'
    probation_frames: int = 20  # ... waits this many frames, then joins if a frame sees its new points where they
    probation_agree: float = 0.9  # ... were on at least this share of those it sees (0 keyframe_colour: none wait)


@dataclass
class GraphConfig:
    """Posture graph optimisation (paper eqs. 7-11)."""

    enabled: bool = True  # False: RANSAC + Kabsch only (ablation "w/o posture graph")
    w_f: float = 1.0  # weight of L_3D, matched 3D features
    w_p: float = 1.0  # weight of L_2D, projective point-to-plane
    w_s: float = 1.0  # weight of L_SDF, once the field has converged
    huber_delta: float = 0.005  # m
    iterations: int = 7  # Gauss-Newton steps for a frame without a given mask (predicted, or a region while lost)
    given_mask_iterations: int = 4  # for a frame that came with its mask (no mask made again at the pose reached)
    depth_downscale: int = 2  # projective association on depth downscaled by this factor (at 640 px width)
    assoc_dist: float = 0.02  # m gate of projective association
    assoc_normal_deg: float = 45.0
    adjacent: int = 2  # adjacent (previous) frames always in the graph
    max_assoc_points: int = 2000  # per node, strided subsample of the valid grid points used by L_2D and L_SDF
    damping: float = 1e-4  # Levenberg-Marquardt-style damping, relative to the diagonal of the normal equations
    w_m: float = 1.0  # prior at the coarse pose where the data leave it free, in point residuals (not in the paper)
    prior_lever: float = 0.02  # m: the prior weighs a rotation as the displacement of a point this far away
    prior_null: float = 0.05  # the prior acts along directions whose data information is below this of the largest
    unmeasured_ratio: float = 1e-3  # below this of the largest, a direction is reported unmeasured (track.jsonl)
    w_fs: float = 1.0  # weight of L_FS, model points the frame saw past pulled into its mask (not in the paper; 0: off)
    free_space_tol: float = 0.01  # m: the frame's depth lies this far behind a model point: it saw past the point
    free_space_margin: float = 2.0  # pixels off the mask before L_FS acts (mask edges, mixed depth)
    free_space_points: int = 1500  # model points (strided) that L_FS projects
    free_space_predicted: bool = False  # L_FS also on frames that came without a mask (predicted masks)
    free_space_background: float = 0.05  # m: without a mask, L_FS on given masks' points vs. the background
    w_cv: float = 1.0  # weight of L_CV, the frame's points the first keyframe saw past pulled into its mask (0: off)
    coverage_points: int = 1000  # frame points (strided) that L_CV projects into the first keyframe
    coverage_gate: float = 0.02  # m: a point further into the keyframe's free space shows a wrong pose, not a slide
    coverage_min_share: float = 0.0  # L_CV only on frames with this share of the first keyframe's points at least
    coverage_predicted: bool = False  # L_CV also on frames that came without a mask (predicted masks)


@dataclass
class FailureConfig:
    """Lost-instrument detection (Stage 2, step 5)."""

    min_pixels: int = 150  # fewer instrument pixels with valid depth: lost
    min_global_overlap: float = 0.6  # re-localisation by FPFH registration must explain this fraction of points
    relocalise_window: int = 15  # frames after a loss in which re-acquisition from the last pose is also tried
    relocalise_every: int = 3  # after relocalise_window lost frames, re-localisation is tried on every n-th frame
    relocalise_candidates: int = 3  # feature RANSAC poses (and FPFH seeds) that compete in re-localisation
    relocalise_prior_null: float = 0.01  # graph.prior_null for re-localisation candidates (prior at each candidate)
    relocalise_w_m: float = 10.0  # graph.w_m for re-localisation candidates: a candidate is held where it was found
    relocalise_max_speed: float = 0.1  # m a frame the origin can have moved while lost (re-localisation's reach)
    relocalise_max_reach: float = 0.2  # m, the reach grows with the frames lost up to this (0: no cap)
    relocalise_max_fit: float = 0.005  # m, median distance of a re-localised frame's points to the model
    search_regions: int = 4  # no mask while lost: colour regions nearest the last position tried for re-localisation
    search_max_span: float = 3.0  # no mask while lost: a colour region wider across the view than this many times
    # the model (geometry.span) is not the instrument (0: no bound)
    relocalise_min_iou: float = 0.12  # no mask while lost: least IoU of the model's silhouette with its region
    relocalise_colour: float = 0.8  # no mask while lost: the mask made at a found pose must score this share of
    # the colour (TrackResult.colour) the masks of the last tracked frames scored, their median (0: off)
    relocalise_min_ncc: float = 0.2  # appearance: least intensity NCC with a keyframe that sees the frame (-1: off)
    appearance_depth_tol: float = 0.005  # m, a frame's point is seen by a keyframe when its depth agrees this well
    appearance_min_points: int = 100  # fewer points seen by every keyframe: no appearance check
    min_confidence: float = 0.25  # fewer of the frame's points on the model at the pose: lost (unsure)
    moved_min_confidence: float = 0.7  # likewise after a jump beyond ransac.check_jump_trans or check_jump_rot_deg
    # from the last tracked pose: a pose carried off along what a small visible part leaves free (0: off)
    # Lost when the frame sees past the model (by graph.free_space_tol) over more than max_seen_past of its
    # silhouette (masking.seen_past) on seen_past_frames frames in a row: the pose is on something else.
    max_seen_past: float = 0.6  # share of the silhouette (1.0: off)
    seen_past_frames: int = 3
    seen_past_given: bool = True  # also on frames that came with their mask (False: frames without a mask only)
    slide_step: float = 0.01  # m: the first pose against a registered model, found by geometry alone, is slid along
    # the model's long axis in these steps to where its silhouette best fits the first mask (0: off)


@dataclass
class SDFConfig:
    """Instrument SDF Psi (Stage 1, paper eqs. 1-4)."""

    enabled: bool = True
    occ_surf: bool = True  # False: no occlusion handling, every non-instrument ray is free space (ablation)
    voxel_size: float = 0.004  # m
    truncation: float = 0.01  # m, band around the observed depth for V_surf
    delta: float = 0.002  # m, target of Psi on occluded samples (eq. 2)
    surf_behind: float = 0.003  # m, depth of the V_surf band behind the observed surface; below a shaft's radius
    alpha: float = 1.0  # weight of L_occ
    beta: float = 1.0  # weight of L_surf
    w_free: float = 0.1  # free-space term in front of the surface
    w_eik: float = 0.01  # eikonal |grad Psi| = 1
    iterations: int = 200
    lr: float = 0.01  # Adam step, in units of the truncation (the grid stores Psi / truncation)
    occ_dilate: int = 5  # pixels: invalid depth this close to the instrument mask is occluded, not free space
    batch_rays: int = 4096  # rays of each kind (instrument, other) drawn per Adam step
    samples_per_ray: int = 8  # samples in the truncation band per instrument ray, along the box per other ray
    ray_stride: int = 2  # non-instrument pixels are taken on this pixel stride (instrument pixels: all)
    converged_tol: float = 0.05  # converged: the loss fell by less than this fraction over the last quarter of a fit
    refit_every: int = 3  # keyframes added between refits (counted as added: a full pool keeps its size)
    max_views: int = 12  # keyframes (evenly spread over the pool) an incremental refit uses; the final fit uses all
    refit_iterations: int = 60  # Adam steps of a warm-started incremental refit
    min_first_views: int = 4  # background: the first fit waits for this many keyframes (one view is soon outdone)
    converge_rounds: int = 8  # background: until the field converges, each fit goes on this many more times at most
    min_keyframes: int = 4  # L_SDF joins the posture graph once the field is converged on at least this many
    agree_tol: float = 0.003  # m; L_SDF joins a frame only while its points' median |Psi| is below this (0: always)
    background: bool = True  # refit in a worker process (tracking never waits); False refits in line (reproducible)
    refine_poses: bool = False  # refine the keyframe poses jointly with Psi (first keyframe fixed), within bounds:
    refine_trans: float = 0.005  # m, the most a refined keyframe pose moves from its tracked one (per axis)
    refine_rot_deg: float = 3.0  # degrees, the most it turns (per axis of the rotation vector)
    refine_lr: float = 0.02  # Adam step of the pose parameters (tanh space: a fraction of the bound)
    mesh_seen: float = 1.0  # voxels: the mesh keeps the faces this close to the model points (what was seen)
    mesh_floater: float = 0.0  # a mesh piece whose seen area is under this share of the largest's is dropped


@dataclass
class TrackerConfig:
    """Everything the tracker needs; every field has a documented default."""

    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    ransac: RansacConfig = field(default_factory=RansacConfig)
    pool: PoolConfig = field(default_factory=PoolConfig)
    graph: GraphConfig = field(default_factory=GraphConfig)
    failure: FailureConfig = field(default_factory=FailureConfig)
    sdf: SDFConfig = field(default_factory=SDFConfig)
    seed: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    def check(self) -> None:
        """Raise `from_dict`'s ValueError for a setting it would refuse, so that a config built in code
        (``GraphConfig(huber_delta=0)``) meets the checks of one read from a file."""
        TrackerConfig.from_dict(self.to_dict())

    @classmethod
    def from_dict(cls, d: dict) -> TrackerConfig:
        """The config a JSON object of the `to_dict` layout gives, defaults for what it leaves out; a key that is
        not a setting, a value of another type, a negative number, 0 where a size must be positive, or a
        ``preprocess.max_depth`` not above ``min_depth`` raises ValueError naming it (``"graph.w_m"``)."""
        sections = {f.name: f.default_factory for f in fields(cls) if f.default_factory is not MISSING}
        kw = {}
        for k, v in _checked(cls, _settings(d, "the config"), "").items():
            kw[k] = sections[k](**_checked(sections[k], _settings(v, k), f"{k}.")) if k in sections else v
        cfg = cls(**kw)
        near, far = cfg.preprocess.min_depth, cfg.preprocess.max_depth
        if far <= near:  # no depth would be kept
            raise ValueError(f"preprocess.max_depth ({far:g}) must be above preprocess.min_depth ({near:g})")
        return cfg


_TYPES = {"bool": (bool,), "int": (int,), "float": (int, float), "str": (str,)}
_LEAST = {"failure.relocalise_min_ncc": -1.0}  # every other number is a count, size, weight or share: none below 0
# Sizes, counts and scales that 0 would break (a division, an empty histogram or sample, no point kept): above 0.
_POSITIVE = {"preprocess.bilateral_sigma_depth", "preprocess.colour_bins", "preprocess.normal_step",
             "preprocess.max_grazing_deg", "preprocess.max_depth", "pool.max_size", "graph.huber_delta",
             "graph.prior_lever", "sdf.voxel_size", "sdf.truncation", "sdf.batch_rays", "sdf.samples_per_ray",
             "sdf.refit_every"}


def _settings(d: object, name: str) -> dict:
    if not isinstance(d, dict):
        raise ValueError(f"{name} must be a JSON object of settings, got {type(d).__name__}")
    return d


def _checked(holder: type, d: dict, prefix: str) -> dict:
    """``d`` when each of its keys is a field of the dataclass ``holder`` with a value of the field's type (a
    section's value is checked by its own call)."""
    kinds = {f.name: f.type for f in fields(holder)}
    for k, v in d.items():
        if k not in kinds:
            raise ValueError(f"unknown config key {prefix + k!r}")
        kind = kinds[k] if isinstance(kinds[k], str) else kinds[k].__name__
        types = _TYPES.get(kind)
        if types is not None and (not isinstance(v, types) or (isinstance(v, bool) and bool not in types)):
            raise ValueError(f"{prefix}{k} must be {kind}, got {v!r}")
        least = _LEAST.get(prefix + k, 0.0)
        if kind in ("int", "float") and not v >= least:
            raise ValueError(f"{prefix}{k} must be at least {least:g}, got {v!r}")
        if prefix + k in _POSITIVE and not v > 0:
            raise ValueError(f"{prefix}{k} must be above 0, got {v!r}")
    return d
