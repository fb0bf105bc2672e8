"""Lost and found: a full occlusion is reported lost, tracking resumes when the instrument reappears, and a
re-localisation that the model does not fit, or whose markings do not match the keyframes', is refused."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import surgtrack.tracker
from surgtrack.config import TrackerConfig
from surgtrack.geometry import inv_T, make_T, project, rotation_angle_deg, span, transform
from surgtrack.global_registration import FpfhCloud
from surgtrack.io import open_sequence
from surgtrack.masking import render_depth
from surgtrack.metrics import auc, evaluate
from surgtrack.pipeline import track_sequence
from surgtrack.synth import SynthSpec, render_sequence
from surgtrack.tracker import HIDDEN, LOST, NO_POSE, NOT_TRIED, RELOCALISED, SEEN_PAST, SurgTracker


@pytest.fixture(scope="module")
def occluded_seq(tmp_path_factory):
    """40 frames; a hand covers the whole probe from frame 15 for 10 frames while it keeps moving."""
    spec = SynthSpec(instrument="ultrasound_probe", frames=40, width=320, height=240, n_occluders=1, seed=21,
                     full_occlusions=((15, 10),), depth_range=(0.25, 0.45))
    return render_sequence(spec, tmp_path_factory.mktemp("occ") / "probe")


def test_full_occlusion_is_lost_then_relocalised(occluded_seq, tmp_path):
    seq = open_sequence(occluded_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    track_sequence(seq, tmp_path, cfg)
    lines = [json.loads(x) for x in (tmp_path / "track.jsonl").read_text().splitlines()]
    status = [x["status"] for x in lines]
    visible = np.array([seq[i].mask.sum() for i in range(len(seq))])
    hidden = np.nonzero(visible == 0)[0]
    assert len(hidden) >= 10
    assert all(status[i] == "lost" for i in hidden)  # never a made-up pose while nothing is seen
    # each lost line says why: nothing to see, or not looked for on that frame (a long loss)
    assert {lines[i]["reason"] for i in hidden} <= {HIDDEN, NOT_TRIED}
    assert lines[hidden[0]]["reason"] == HIDDEN
    assert all("reason" not in x for x in lines if x["status"] != "lost")
    back = next(i for i in range(hidden[-1] + 1, len(seq)) if visible[i] >= 0.5 * visible[0])
    resumed = next(i for i in range(back, len(seq)) if status[i] != "lost")
    assert resumed - back <= 5
    assert status[resumed] == "relocalised"
    m = evaluate(tmp_path, seq)
    rest = [m["errors"]["add_s"][seq.ids[i]] for i in range(resumed + 2, len(seq))]
    assert auc(np.array([np.inf if e is None else e for e in rest])) >= 80


def _relocalising_every_frame() -> TrackerConfig:
    """No field; after a loss, re-localisation on every frame and without the last pose as a candidate."""
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.failure.relocalise_window = 0
    cfg.failure.relocalise_every = 1
    return cfg


def _lost_after(seq, cfg: TrackerConfig) -> tuple[SurgTracker, np.ndarray]:
    """A tracker lost at frame 3 (empty mask) after three tracked frames, and the object-frame alignment to gt."""
    tracker = SurgTracker(cfg)
    first = tracker.register(seq[0], seq[0].mask)
    for i in (1, 2):
        tracker.track(seq[i], seq[i].mask)
    assert tracker.track(seq[3], np.zeros_like(seq[3].mask)).status == LOST
    return tracker, inv_T(first) @ seq.gt_poses()[seq.ids[0]]


def test_a_relocalisation_the_model_does_not_fit_is_refused(synth_seq, monkeypatch):
    """A candidate that turns the shaft end for end (what FPFH can return on a long round instrument) is refused:
    the frame stays lost instead of reporting it and tracking on from it; the true pose is taken."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()  # no last-pose candidate: only the one given below
    cfg.failure.relocalise_min_ncc = -1.0  # the fit check alone (the appearance check: the test below)
    cfg.graph.w_fs = 0.0  # and L_FS, which pulls the model back into the mask, off too: the candidate stays flipped
    frame = seq[4]

    def relocalise(candidate_of, max_fit: float) -> tuple[str, np.ndarray | None]:
        cfg.failure.relocalise_max_fit = max_fit
        tracker, align = _lost_after(seq, cfg)
        true = seq.gt_poses()[frame.id] @ inv_T(align)
        candidate = candidate_of(true, tracker.model_points)
        monkeypatch.setattr(tracker, "_candidates", lambda obs, feats, last: [(candidate, [], 0)])
        result = tracker.track(frame, frame.mask)
        reasons.append(result.reason)
        return result.status, None if result.pose is None else inv_T(true) @ result.pose

    reasons: list[str] = []

    def flipped(true: np.ndarray, model: np.ndarray) -> np.ndarray:
        across = np.linalg.svd(model - model.mean(axis=0))[2][2]  # the model's thinnest direction
        return true @ make_T(Rotation.from_rotvec(np.pi * across).as_matrix(), np.zeros(3))

    status, _ = relocalise(flipped, 0.005)
    assert status == LOST
    assert reasons[-1] == NO_POSE  # the instrument shows; no pose for it passed
    status, error = relocalise(flipped, np.inf)  # without the fit check, this wrong pose would be taken
    assert status == RELOCALISED and rotation_angle_deg(error[:3, :3]) > 90
    status, error = relocalise(lambda true, model: true, 0.005)
    assert status == RELOCALISED and np.linalg.norm(error[:3, 3]) < 0.005


def test_a_relocalisation_that_fits_but_looks_wrong_is_refused(synth_seq, monkeypatch):
    """A candidate at which the frame fits the model's geometry but not its markings (here: the true pose, with
    the frame's intensities inverted, as another instrument of the same shape would look) is refused by the
    appearance check; with the frame as it is, the same pose is taken, its intensities correlating with the
    keyframes'."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    frame = seq[4]

    def relocalise(rgb: np.ndarray) -> tuple[str, float | None]:
        tracker, align = _lost_after(seq, cfg)
        true = seq.gt_poses()[frame.id] @ inv_T(align)
        monkeypatch.setattr(tracker, "_candidates", lambda obs, feats, last: [(true, [], 0)])
        looks: list[float | None] = []
        appearance = tracker._appearance
        monkeypatch.setattr(tracker, "_appearance", lambda *a: looks.append(appearance(*a)) or looks[-1])
        return tracker.track(replace(frame, rgb=rgb), frame.mask).status, looks[0]

    status, looks = relocalise(frame.rgb)
    assert status == RELOCALISED and looks is not None and looks > 0.5
    status, looks = relocalise(255 - frame.rgb)
    assert status == LOST and looks is not None and looks < cfg.failure.relocalise_min_ncc


def test_a_candidate_keeps_where_it_puts_the_shaft(synth_seq, monkeypatch):
    """Re-localised many frames after the loss, the true pose stays true: the graph refines a candidate with its
    motion prior at the candidate itself, not at the last tracked pose (which would pull its slide along the
    shaft, which the frame's geometry leaves free, back to where the shaft was before the loss)."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    tracker, align = _lost_after(seq, cfg)
    frame = seq[len(seq) - 1]
    true = seq.gt_poses()[frame.id] @ inv_T(align)
    moved = inv_T(tracker.recent[-1].pose) @ true
    assert np.linalg.norm(moved[:3, 3]) > 0.02  # the instrument moved on during the loss
    monkeypatch.setattr(tracker, "_candidates", lambda obs, feats, last: [(true, [], 0)])
    result = tracker.track(frame, frame.mask)
    assert result.status == RELOCALISED
    error = inv_T(true) @ result.pose
    assert np.linalg.norm(error[:3, 3]) < 0.005 and rotation_angle_deg(error[:3, :3]) < 5


def test_a_candidate_the_graph_pulls_off_the_model_is_taken_as_found(synth_seq, monkeypatch):
    """The posture graph refines each candidate against the frames before the loss and the keyframes; when that
    leaves the frame further from the model (median distance) than the candidate did, as stale neighbours can,
    the candidate is taken as it was found instead of being refused for the graph's fit. A refinement that
    brings the frame nearer the model is taken."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    frame = seq[4]
    across = make_T(np.eye(3), np.array([0.02, 0.0, 0.0]))  # 2 cm off, in the camera frame

    def relocalise(offset: np.ndarray, pull: bool) -> tuple[str, np.ndarray | None]:
        tracker, align = _lost_after(seq, cfg)
        true = seq.gt_poses()[frame.id] @ inv_T(align)
        monkeypatch.setattr(tracker, "_candidates", lambda obs, feats, last: [(offset @ true, [], 0)])
        if pull:
            monkeypatch.setattr(tracker, "_optimise", lambda node, edges, candidate=False, obs=None: across @ true)
        result = tracker.track(frame, frame.mask)
        monkeypatch.undo()
        return result.status, None if result.pose is None else np.linalg.norm((inv_T(true) @ result.pose)[:3, 3])

    status, error = relocalise(np.eye(4), pull=True)
    assert status == RELOCALISED and error < 1e-6  # the candidate as found, not the graph's pose 2 cm off
    nudged = make_T(np.eye(3), np.array([0.0, 0.004, 0.0]))
    status, error = relocalise(nudged, pull=False)
    assert status == RELOCALISED and error < 0.002  # the graph's refinement, nearer the truth than the candidate


def test_a_relocalisation_further_than_the_instrument_can_have_moved_is_refused(synth_seq, monkeypatch):
    """A candidate is taken only within ``failure.relocalise_max_speed`` times the frames since the last tracked
    one, and never further than ``failure.relocalise_max_reach``: here the true pose, 27 frames after the loss, taken
    under the defaults and refused (the frame stays lost) under a speed, or a cap, half what the instrument really
    needed."""
    seq = open_sequence(synth_seq)
    frame = seq[len(seq) - 1]

    def relocalise(**failure: float) -> tuple[str, float, int]:
        cfg = _relocalising_every_frame()
        cfg.failure = replace(cfg.failure, **failure)
        tracker, align = _lost_after(seq, cfg)
        true = seq.gt_poses()[frame.id] @ inv_T(align)
        monkeypatch.setattr(tracker, "_candidates", lambda obs, feats, last: [(true, [], 0)])
        last = tracker.recent[-1]
        moved = np.linalg.norm((inv_T(last.pose) @ true)[:3, 3])
        return tracker.track(frame, frame.mask).status, moved, frame.index - last.index

    status, moved, frames = relocalise()
    assert status == RELOCALISED and moved > 0
    assert relocalise(relocalise_max_speed=moved / frames / 2)[0] == LOST
    assert relocalise(relocalise_max_reach=moved / 2)[0] == LOST
    assert relocalise(relocalise_max_reach=0.0)[0] == RELOCALISED  # 0: no cap


def test_a_long_loss_without_masks_is_searched_on_every_few_frames_only(synth_seq, monkeypatch):
    """The search without a mask, the costliest step, runs on every frame of the window after a loss, then on every
    ``relocalise_every``-th: the frames between are reported lost at once ("not tried"). A frame that comes with its
    mask is tried whenever the mask shows the instrument, and taken when it fits; an empty mask is "hidden"."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.failure.relocalise_window, cfg.failure.relocalise_every = 4, 3
    tracker, _ = _lost_after(seq, cfg)
    tried = []
    monkeypatch.setattr(tracker, "_search", lambda frame, colour, clock: tried.append(tracker.frames_lost) or NO_POSE)
    frame = seq[4]
    results = [tracker.track(frame, None) for _ in range(10)]
    assert [r.status for r in results] == [LOST] * 10
    assert tried == [1, 2, 3, 4, 7, 10]  # lost frames before each try: the window, then every third
    assert [r.reason for r in results] == [NO_POSE if n in tried else NOT_TRIED for n in range(1, 11)]
    empty = tracker.track(frame, np.zeros_like(frame.mask))
    assert (empty.status, empty.reason) == (LOST, HIDDEN)
    assert not tracker._relocalisation_due()  # a mask-less frame would not be searched now; this one has its mask
    assert tracker.track(frame, frame.mask).status == RELOCALISED


def test_relocalisation_registers_against_the_model_as_it_is_now(synth_seq):
    """Global registration after a loss uses the model's FPFH features computed once (a loss tries several regions
    a frame against the same model), and computed again once keyframes have added points to the model: never the
    features of a model the tracker no longer has. The same for the model's span, which bounds the search's
    regions."""
    seq = open_sequence(synth_seq)
    tracker = SurgTracker(TrackerConfig.from_dict({"sdf": {"enabled": False}}))
    tracker.register(seq[0], seq[0].mask)
    first, first_span = tracker._model_features(), tracker._span()
    assert tracker._model_features() is first and first_span == span(tracker.model_points)
    before = tracker.model_points
    for i in range(1, len(seq)):
        tracker.track(seq[i], None)
        if tracker.model_points is not before:
            break
    assert tracker.model_points is not before and len(tracker.model_points) > len(before)
    now = tracker._model_features()
    assert now is not first and now.source is tracker.model_points and tracker._model_features() is now
    assert np.array_equal(np.asarray(now.cloud.points), np.asarray(FpfhCloud.of(tracker.model_points).cloud.points))
    assert tracker._span() == span(tracker.model_points) != first_span


def test_without_masks_a_nearer_look_alike_does_not_take_the_relocalisation(synth_seq):
    """Lost with no mask given, the search tries the colour regions nearest the last position and takes the pose
    whose model silhouette agrees best with its region. Here the instrument has moved 40 px across the image, and a
    piece of it (a fingertip-sized region of its colour) lies where it was: nearest, and a part of the model fits
    it. Trying only the nearest region, the frame stays lost (no pose on the piece is taken); trying the nearest
    four, the instrument is found where it moved."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    frame = seq[4]
    v, u = np.nonzero(frame.mask)
    shaft = np.linalg.eigh(np.cov(np.stack([u, v])))[1][:, -1]  # the shaft's direction in the image
    du, dv = np.round(40 * np.array([-shaft[1], shaft[0]])).astype(int)  # across it
    moved = replace(frame, rgb=np.roll(frame.rgb, (dv, du), axis=(0, 1)),
                    depth=np.roll(frame.depth, (dv, du), axis=(0, 1)))
    tracker, _ = _lost_after(seq, cfg)
    u0, v0 = project(tracker.recent[-1].pose[:3, 3][None], frame.K)[0][0]
    v, u = np.mgrid[: frame.depth.shape[0], : frame.depth.shape[1]]
    piece = frame.mask & (np.abs(u - u0) < 20) & (np.abs(v - v0) < 20) & (frame.depth > 0)
    assert cfg.failure.min_pixels <= piece.sum() < 0.3 * frame.mask.sum()
    moved.rgb[piece], moved.depth[piece] = frame.rgb[piece], frame.depth[piece]

    def relocalised(regions: int) -> np.ndarray | None:
        cfg.failure.search_regions = regions
        tracker, _ = _lost_after(seq, cfg)
        result = tracker.track(moved, None)
        return result.pose if result.status == RELOCALISED else None

    assert relocalised(1) is None
    pose = relocalised(4)
    assert pose is not None
    u1, v1 = project(pose[:3, 3][None], frame.K)[0][0]
    assert np.hypot(u1 - (u0 + du), v1 - (v0 + dv)) < 6


def test_without_masks_the_search_starts_where_the_instrument_was_last_seen(synth_seq, monkeypatch):
    """The colour regions are ranked by their distance to where the instrument was last seen: the last tracked
    frame's points, not its object origin (the first frame's centroid), which lies mid-shaft when only one end of
    the shaft showed last."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    cfg.failure.min_pixels = 50  # one end of a shaft at 320 x 240
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    tracker.track(seq[1], seq[1].mask)
    frame = seq[2]
    v, u = np.nonzero(frame.mask)
    shaft = np.linalg.eigh(np.cov(np.stack([u, v])))[1][:, -1]
    u0, v0 = project(tracker.recent[-1].pose[:3, 3][None], frame.K)[0][0]
    along = (u - u0) * shaft[0] + (v - v0) * shaft[1]
    end = frame.mask.copy()
    end[v, u] = along > 30 if (along > 30).sum() > (along < -30).sum() else along < -30  # one end, 30 px on
    assert tracker.track(frame, end).status != LOST
    pts = tracker.recent[-1].xyz[tracker.recent[-1].xyz[..., 2] > 0]
    seen = np.median(pts, axis=0)
    origin = tracker.recent[-1].pose[:3, 3]
    assert np.linalg.norm(origin - seen) > 0.02
    assert tracker.track(seq[3], np.zeros_like(seq[3].mask)).status == LOST

    centres = []
    search = surgtrack.tracker.search_regions

    def recorded(posterior, depth, K, centre, *args, **kwargs):  # noqa: ANN001, ANN202 - a transparent wrapper
        centres.append(np.array(centre))
        return search(posterior, depth, K, centre, *args, **kwargs)

    monkeypatch.setattr(surgtrack.tracker, "search_regions", recorded)
    tracker.track(seq[4], None)
    assert len(centres) == 1
    assert np.linalg.norm(centres[0] - seen) < 0.005


def test_a_pose_the_camera_sees_through_is_reported_lost(synth_seq):
    """From frame 4 the instrument is gone (the frame sees 5 cm past where it was) but for a piece of it that stays
    where frame 3 had it, like a fingertip of its colour at its depth. The model fits the piece, so frame by frame
    a pose holds; but the camera sees through most of the model's silhouette there, and after
    ``failure.seen_past_frames`` such frames (two here) the tracker says it has lost the instrument. With the check
    off it reports every one of those frames tracked. Frames that come with their mask (here the piece's) are
    checked only with ``failure.seen_past_given``."""
    seq = open_sequence(synth_seq)
    last = seq[3]
    v, u = np.mgrid[: last.depth.shape[0], : last.depth.shape[1]]

    def statuses(max_seen_past: float, given: bool = False, check_given: bool = False) -> list[str]:
        cfg = TrackerConfig()
        cfg.sdf.enabled = False
        cfg.failure.max_seen_past = max_seen_past
        cfg.failure.seen_past_frames = 2
        cfg.failure.seen_past_given = check_given
        cfg.graph.w_fs = 0.0  # L_FS would pull a frame with its mask off the piece, and it would be lost at once
        cfg.failure.min_pixels = 30  # a piece of a shaft at 320 x 240
        tracker = SurgTracker(cfg)
        tracker.register(seq[0], seq[0].mask)
        assert all(tracker.track(seq[i], None).status != LOST for i in range(1, 4))
        u0, v0 = project(tracker.recent[-1].pose[:3, 3][None], last.K)[0][0]
        piece = last.mask & (np.abs(u - u0) < 17) & (np.abs(v - v0) < 17) & (last.depth > 0)
        assert 0.1 * last.mask.sum() < piece.sum() < 0.2 * last.mask.sum()
        out = []
        for i in range(4, 10):
            frame = seq[i]
            depth = np.where(frame.mask, frame.depth + 0.05 * (frame.depth > 0), frame.depth)
            depth[piece] = last.depth[piece]
            rgb = frame.rgb.copy()
            rgb[piece] = last.rgb[piece]
            result = tracker.track(replace(frame, rgb=rgb, depth=depth), piece if given else None)
            if result.status == LOST and LOST not in out:
                assert result.reason == SEEN_PAST  # the piece shows and the model fits it
            out.append(result.status)
        return out

    default = TrackerConfig().failure.max_seen_past
    assert LOST not in statuses(1.0)
    assert LOST in statuses(default)[:2]
    assert LOST not in statuses(default, given=True)
    assert LOST in statuses(default, given=True, check_given=True)[:2]


def test_the_pose_a_loss_saw_through_is_not_offered_again(synth_seq, monkeypatch):
    """Within ``failure.relocalise_window`` frames of a loss the last tracked pose competes in re-localisation, unless
    the loss began with the camera seeing through the model at it (`SEEN_PAST`): taken again, it would be lost again
    by the same check a few frames later."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False

    def offered_after(reason: str) -> tuple[np.ndarray, list[np.ndarray]]:
        tracker = SurgTracker(cfg)
        tracker.register(seq[0], seq[0].mask)
        for i in (1, 2):
            tracker.track(seq[i], seq[i].mask)
        if reason == SEEN_PAST:
            tracker._sees_past = lambda obs, pose: True  # the check itself: the test above
            lost = tracker.track(seq[3], seq[3].mask)
            del tracker._sees_past
        else:
            lost = tracker.track(seq[3], np.zeros_like(seq[3].mask))
        assert (lost.status, lost.reason) == (LOST, reason)
        seen: dict = {}
        best = tracker._best_candidate

        def competing(obs, feats, cands, last):
            seen.update(last=last, offered=[c[0] for c in cands])
            return best(obs, feats, cands, last)

        monkeypatch.setattr(tracker, "_best_candidate", competing)
        tracker.track(seq[4], seq[4].mask)
        return seen["last"], seen["offered"]

    last, offered = offered_after(HIDDEN)
    assert any(np.array_equal(c, last) for c in offered)
    last, offered = offered_after(SEEN_PAST)
    assert offered and not any(np.array_equal(c, last) for c in offered)


def _ghost_beside(tracker: SurgTracker, pose: np.ndarray, mask: np.ndarray, offset: float) -> np.ndarray:
    """The tracker's model points moved ``offset`` m across the shaft (in the image plane), added to its model as a
    predicted-mask keyframe would add fingers beside the instrument; returns them in the object frame."""
    v, u = np.nonzero(mask)
    shaft = np.linalg.eigh(np.cov(np.stack([u, v])))[1][:, -1]
    across = pose[:3, :3].T @ np.array([-shaft[1], shaft[0], 0.0])  # in the image plane, object frame
    ghost = tracker.model_points + offset * across
    tracker._remember_points(SimpleNamespace(pose=pose, xyz=transform(pose, ghost)[:, None]), given=False)
    return ghost


def test_without_masks_what_the_camera_sees_past_leaves_the_model(synth_seq):
    """A predicted mask can take in what is not the instrument (fingers at its depth), and its keyframe adds it to
    the model. Here a copy of the first frame's points 2 cm beside the instrument joins the model as such a keyframe
    would add it. Tracked frames without a mask see past it to the background; with ``pool.carve_ratio`` set it
    leaves the model once ``pool.carve_min_views`` frames have seen it (here three quarters of it in nine frames),
    while the first frame's points (its mask was given) all stay. Without carving the copy stays."""
    seq = open_sequence(synth_seq)

    def model_after(carve_ratio: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg = TrackerConfig()
        cfg.sdf.enabled = False
        cfg.pool.carve_ratio = carve_ratio
        tracker = SurgTracker(cfg)
        pose = tracker.register(seq[0], seq[0].mask)
        first = tracker.model_points.copy()
        ghost = _ghost_beside(tracker, pose, seq[0].mask, 0.02)
        assert all(tracker.track(seq[i], None).status != LOST for i in range(1, 10))
        return first, ghost, tracker.model_points

    def share_kept(points: np.ndarray, model: np.ndarray) -> float:
        return float(np.mean(cKDTree(model).query(points)[0] < 1e-6))

    first, ghost, model = model_after(0.5)
    assert share_kept(first, model) == 1.0
    assert share_kept(ghost, model) < 0.4  # what stays, the frames did not see (out of view, behind the hand)
    _, ghost, model = model_after(0.0)
    assert share_kept(ghost, model) > 0.9


def test_without_masks_the_predicted_mask_stays_within_the_first_masks_reach_across_the_shaft(synth_seq):
    """Something at the instrument's depth beside its shaft (fingers that hold it) gets into a predicted mask where
    the model has grown into it. Here the model holds a copy of the first frame's points 4 cm beside the shaft,
    and the frame shows a surface there at the copy's depth, of a colour the colour gates let through (turned off
    here). With ``preprocess.predicted_mask_across`` the mask keeps to the first mask's reach across the shaft plus
    that margin: the surface stays out and the instrument's own pixels stay in; without it the mask takes the
    surface in."""
    seq = open_sequence(synth_seq)
    frame = seq[1]

    def predicted(across: float) -> tuple[np.ndarray, np.ndarray]:
        cfg = TrackerConfig()
        cfg.sdf.enabled = False
        cfg.preprocess.predicted_mask_across = across
        cfg.preprocess.predicted_mask_colour = cfg.preprocess.predicted_mask_colour_inside = 0.0  # colour alike
        tracker = SurgTracker(cfg)
        pose = tracker.register(seq[0], seq[0].mask)
        ghost = _ghost_beside(tracker, pose, seq[0].mask, 0.04)
        surface = render_depth(ghost, pose, frame.K, frame.depth.shape)
        depth = np.where((surface > 0) & ~frame.mask, surface, frame.depth)
        shown = replace(frame, depth=depth)
        return tracker._predicted_mask(shown, pose), (surface > 0) & ~frame.mask & (depth > 0)

    def inside(mask: np.ndarray, where: np.ndarray) -> float:
        return float(np.mean(mask[where]))

    bounded, surface = predicted(0.01)
    assert inside(bounded, surface) < 0.05
    assert inside(bounded, seq[1].mask & (seq[1].depth > 0)) > 0.85
    unbounded, _ = predicted(0.0)
    assert inside(unbounded, surface) > 0.5


def test_without_masks_a_region_of_the_first_frames_colours_with_broken_depth_grows_into_the_rest(synth_seq):
    """Lost with no mask given. The instrument is back where it was, but the first frame's colours show only on a
    stretch of it whose depth the sensor breaks up (every other pixel, as on bright metal); the rest of it shows a
    colour the first frame did not (posterior near 0.5, below the search's threshold), with its depth. The colour
    region alone has no trusted points to re-localise on and the frame stays lost; grown into the pixels of
    middling posterior around it (``preprocess.search_grow_colour``), it is re-localised where the instrument is."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    cfg.failure.min_pixels = 60  # a thin shaft at 320 x 240
    frame = seq[4]
    v, u = np.nonzero(frame.mask & (frame.depth > 0))
    shaft = np.linalg.eigh(np.cov(np.stack([u, v])))[1][:, -1]
    along = (u - u.mean()) * shaft[0] + (v - v.mean()) * shaft[1]
    strip = np.abs(along) < 40  # about half the shaft in view
    rgb, depth = frame.rgb.copy(), frame.depth.copy()
    rgb[v[~strip], u[~strip]] = (200, 40, 200)  # a colour no part of the first frame had
    broken = strip & ((u + v) % 2 == 1)
    depth[v[broken], u[broken]] = 0.0
    later = replace(frame, rgb=rgb, depth=depth)

    def pose_found(grow: float) -> np.ndarray | None:
        cfg.preprocess.search_grow_colour = grow
        tracker, align = _lost_after(seq, cfg)
        posterior = tracker.colour.posterior(rgb[v[~strip], u[~strip]])
        assert 0.4 <= posterior.min() and posterior.max() < cfg.preprocess.search_mask_colour
        result = tracker.track(later, None)
        return None if result.status != RELOCALISED else result.pose @ align

    assert pose_found(0.0) is None
    pose = pose_found(0.4)
    assert pose is not None
    gt = seq.gt_poses()[frame.id]
    assert np.linalg.norm(pose[:3, 3] - gt[:3, 3]) < 0.01 and rotation_angle_deg(pose[:3, :3].T @ gt[:3, :3]) < 5


def test_without_masks_a_relocalisation_whose_mask_looks_unlike_the_instrument_before_is_refused(synth_seq,
                                                                                                monkeypatch):
    """Lost without a mask, a pose found again must make a mask that looks as much like the instrument (its colour,
    `TrackResult.colour`) as the masks of the frames tracked before the loss did, by ``failure.relocalise_colour``
    of theirs. Here the pose is found on the part of the instrument that keeps its colours while the rest of what
    the pose covers shows a colour the first frame never did (like a hand of another colour where the pose puts the
    instrument): refused, the frame stays lost; with the check off it is taken. The frame as it is, re-found at
    the same pose, is taken with the check on."""
    seq = open_sequence(synth_seq)
    cfg = _relocalising_every_frame()
    frame = seq[4]
    v, u = np.nonzero(frame.mask & (frame.depth > 0))
    shaft = np.linalg.eigh(np.cov(np.stack([u, v])))[1][:, -1]
    along = (u - u.mean()) * shaft[0] + (v - v.mean()) * shaft[1]
    painted = frame.rgb.copy()
    far = along > np.quantile(along, 0.3)  # 70 % of the instrument along its shaft
    painted[v[far], u[far]] = (255, 0, 255)

    def relocalise(rgb: np.ndarray, share: float) -> tuple[str, str, list[float]]:
        cfg.failure.relocalise_colour = share
        tracker = SurgTracker(cfg)
        first = tracker.register(seq[0], seq[0].mask)
        for i in (1, 2):
            assert tracker.track(seq[i], None).status != LOST
        assert tracker.track(seq[3], np.zeros_like(seq[3].mask)).status == LOST
        true = seq.gt_poses()[frame.id] @ inv_T(inv_T(first) @ seq.gt_poses()[seq.ids[0]])
        monkeypatch.setattr(tracker, "_candidates", lambda obs, feats, last: [(true, [], 0)])
        assert 0.4 < tracker.colour.posterior(np.array([[255, 0, 255]], np.uint8))[0] < 0.6  # a colour never seen
        result = tracker.track(replace(frame, rgb=rgb), None)
        return result.status, result.reason, list(tracker.colours)

    status, reason, before = relocalise(painted, 0.8)
    assert len(before) == 2 and min(before) > 0.8
    assert status == LOST and reason == NO_POSE
    assert relocalise(painted, 0.0)[0] == RELOCALISED
    assert relocalise(frame.rgb, 0.8)[0] == RELOCALISED
