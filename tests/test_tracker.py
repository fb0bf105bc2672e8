"""The tracker's public behaviour: object frame, lost frames, end-to-end accuracy on a rendered sequence."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh
from helpers import tracked

from surgtrack.config import TrackerConfig
from surgtrack.geometry import backproject, depth_to_xyz, make_T, transform
from surgtrack.io import SequenceError, format_pose, open_sequence, read_poses
from surgtrack.metrics import evaluate
from surgtrack.pipeline import RunSummary, track_sequence
from surgtrack.posture_graph import Unmeasured
from surgtrack.tracker import (
    HIDDEN,
    LOST,
    NO_DEPTH,
    RELOCALISED,
    TRACKED,
    UNSURE,
    SurgTracker,
    TrackResult,
    object_origin,
    shaft_range,
)


def test_object_origin_ignores_outliers():
    rng = np.random.default_rng(0)
    shaft = np.column_stack([rng.uniform(-0.1, 0.1, 2000), 0.004 * rng.standard_normal((2000, 2))]) + [0, 0, 0.4]
    flying = rng.uniform(-1, 1, (100, 3)) + [0, 0, 1.5]
    np.testing.assert_allclose(object_origin(np.vstack([shaft, flying])), shaft.mean(axis=0), atol=0.003)


def test_the_final_box_grows_along_the_shaft_the_keyframes_saw():
    """The mesh's box takes in the shaft later keyframes show, not a drifted keyframe's stray points nor things
    beside the instrument; the field's values carry over and the cross-section stays the first frame's."""
    from scipy.spatial.transform import Rotation

    from surgtrack.config import SDFConfig
    from surgtrack.registration import InstrumentSDF

    rng = np.random.default_rng(0)
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix().T  # rows: the box's axes
    psi = InstrumentSDF(SDFConfig(), np.zeros(3), np.array([0.12, 0.03, 0.03]), rotation=R)
    psi.psi = torch.rand(psi.grid.shape, generator=torch.Generator().manual_seed(0))
    psi.weight = torch.ones(psi.grid.shape)
    shaft = np.column_stack([rng.uniform(-0.05, 0.25, 5000), 0.004 * rng.standard_normal((5000, 2))])
    stray = np.column_stack([rng.uniform(0.3, 0.7, 60), np.zeros((60, 2))])  # 1 %: a drifted keyframe
    beside = np.column_stack([rng.uniform(-0.5, -0.3, 2000), np.full(2000, 0.1), np.zeros(2000)])  # out of section
    lo, hi = shaft_range(psi, np.vstack([shaft, stray, beside]) @ R)  # box frame -> object frame
    assert -0.07 < lo <= psi.grid.origin[0] and 0.25 < hi < 0.28
    longer = psi.lengthened(lo, hi)
    v = longer.grid.voxel
    assert 0 <= lo - longer.grid.origin[0] < v and 0 <= longer.grid.upper[0] - hi < v
    k, n = round((psi.grid.origin[0] - longer.grid.origin[0]) / v), psi.grid.shape[0]
    np.testing.assert_allclose(longer.grid.origin, psi.grid.origin - [k * v, 0, 0])
    assert longer.grid.shape[1:] == psi.grid.shape[1:]
    torch.testing.assert_close(longer.psi[k:k + n], psi.psi)
    assert (longer.weight[k + n:] == 0).all() and (longer.psi[k + n:] == 1).all() and (longer.weight[:k] == 0).all()
    p = transform(make_T(R.T, np.zeros(3)), np.array([[0.01, 0.005, -0.004]]))  # a point in both boxes
    np.testing.assert_allclose(longer.query(p)[0], psi.query(p)[0], atol=1e-6)
    lo, hi = shaft_range(psi, np.column_stack([np.linspace(-1, 1, 1000), np.zeros((1000, 2))]) @ R)
    assert hi - lo == pytest.approx(0.8)


def test_first_pose_is_the_masked_cloud_centre_with_camera_axes(synth_seq):
    seq = open_sequence(synth_seq)
    frame = seq[0]
    pose = SurgTracker().register(frame, frame.mask)
    np.testing.assert_allclose(pose[:3, :3], np.eye(3))
    pts, _ = backproject(frame.depth, frame.K, frame.mask)
    np.testing.assert_allclose(pose[:3, 3], object_origin(pts))
    assert np.linalg.norm(pose[:3, 3] - pts.mean(axis=0)) < 0.02  # outliers removed, not the bulk


def test_empty_mask_frame_is_lost_not_a_made_up_pose(synth_seq):
    seq = open_sequence(synth_seq)
    tracker = SurgTracker()
    tracker.register(seq[0], seq[0].mask)
    result = tracker.track(seq[1], np.zeros_like(seq[1].mask))
    assert result.status == LOST
    assert result.pose is None
    assert result.reason == HIDDEN
    # The next frame with its mask is found again.
    again = tracker.track(seq[2], seq[2].mask)
    assert again.status == "relocalised" and again.pose is not None


def test_a_frame_whose_mask_shows_the_instrument_without_depth_is_lost_for_want_of_depth(synth_seq):
    """Specular metal or a sensor too near leaves the mask without depth: the frame is lost "no depth", not
    "hidden", whether it comes while tracking or while lost."""
    seq = open_sequence(synth_seq)
    tracker = SurgTracker()
    tracker.register(seq[0], seq[0].mask)
    for i in (1, 2):
        frame = seq[i]
        dry = replace(frame, depth=np.where(frame.mask, 0, frame.depth).astype(frame.depth.dtype))
        result = tracker.track(dry, frame.mask)
        assert (result.status, result.reason, result.pose) == (LOST, NO_DEPTH, None)
    assert tracker.track(seq[3], seq[3].mask).status == RELOCALISED


def test_a_pose_too_few_of_whose_points_lie_on_the_model_is_lost_as_unsure(synth_seq):
    """Below ``failure.min_confidence`` (the share of the frame's points on the model) a pose is not reported; the
    result says why and keeps the confidence it had."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    assert tracker.track(seq[1], seq[1].mask).confidence > 0.9
    cfg.failure.min_confidence = 1.01  # no pose can reach it
    result = tracker.track(seq[2], seq[2].mask)
    assert (result.status, result.reason, result.pose) == (LOST, UNSURE, None)
    assert result.confidence > 0.9


def _padded(frame, share: float) -> np.ndarray:
    """The frame's mask with ``share`` of its pixel count added from the background farthest from it."""
    mask = frame.mask.copy()
    background = np.argwhere(~mask & (frame.depth > 0))
    far = np.linalg.norm(background - np.argwhere(mask).mean(axis=0), axis=1)
    pick = background[np.argsort(-far)[: int(mask.sum() * share)]]
    mask[pick[:, 0], pick[:, 1]] = True
    return mask


def test_a_pose_that_moved_far_with_much_of_the_frame_off_the_model_is_lost_as_unsure(synth_seq):
    """A frame over a third of whose points the model lacks is tracked at the instrument's pace (a part coming into
    view), but not after a jump beyond ``ransac.check_jump_*``: below ``failure.moved_min_confidence`` that is a
    pose carried off, lost as unsure. The same jump with a clean mask is tracked."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False

    def after_ten() -> SurgTracker:
        tracker = tracked(seq, cfg, 10)
        assert not tracker.lost
        return tracker

    result = after_ten().track(seq[10], _padded(seq[10], 0.6))
    assert result.status == TRACKED and result.confidence < cfg.failure.moved_min_confidence
    result = after_ten().track(seq[25], _padded(seq[25], 0.6))
    assert (result.status, result.reason, result.pose) == (LOST, UNSURE, None)
    assert cfg.failure.min_confidence < result.confidence < cfg.failure.moved_min_confidence
    assert after_ten().track(seq[25], seq[25].mask).status == TRACKED


def test_register_rejects_a_mask_without_depth(synth_seq):
    frame = open_sequence(synth_seq)[0]
    with pytest.raises(ValueError, match="instrument pixels"):
        SurgTracker().register(frame, np.zeros_like(frame.mask))


def test_tracks_a_synthetic_sequence_within_stated_error(synth_seq, tmp_path):
    """Per-frame masks, default config: ADD-S AUC >= 85 and ADD AUC >= 70 on the 30-frame occluded sequence."""
    seq = open_sequence(synth_seq)
    summary = track_sequence(seq, tmp_path / "out", TrackerConfig())
    assert summary.frames == len(seq)
    assert len(read_poses(tmp_path / "out" / "ob_in_cam")) == len(seq) - summary.lost
    lines = [json.loads(x) for x in (tmp_path / "out" / "track.jsonl").read_text().splitlines()]
    assert [x["frame"] for x in lines] == seq.ids
    m = evaluate(tmp_path / "out", seq)
    assert m["add_s_auc"] >= 85, m["add_s_auc"]
    assert m["add_auc"] >= 70, m["add_auc"]


def test_each_posed_frame_says_what_its_data_left_unmeasured_the_turn_about_a_round_shaft(synth_seq, tmp_path):
    """track.jsonl's ``unmeasured`` on a rigid endoscope's round shaft: turns only, about the shaft's own axis
    (object frame: the camera's axes at the first frame), on some frames; lost frames carry no such list."""
    from surgtrack.synth.instruments import load_instrument

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    track_sequence(seq, tmp_path / "out", cfg)
    lines = [json.loads(x) for x in (tmp_path / "out" / "track.jsonl").read_text().splitlines()]
    assert all(("unmeasured" in x) == (x["status"] != LOST) for x in lines)
    shaft = seq.gt_poses()[seq.ids[0]][:3, :3] @ load_instrument("rigid_endoscope").axis
    free = [u for x in lines for u in x.get("unmeasured", [])]
    assert len(free) >= 3
    assert all(list(u) == ["turn"] for u in free)
    assert all(abs(np.dot(u["turn"], shaft)) > np.cos(np.radians(3.0)) for u in free)


def test_a_broken_frame_stops_the_run_with_its_name_and_keeps_the_poses_before(synth_seq, tmp_path):
    """The frames are read ahead while earlier ones are tracked (`Sequence.read_ahead`): an unreadable frame still
    stops the run at that frame, with an error naming its file, and the poses of the frames before it stay written."""
    root = tmp_path / "seq"
    shutil.copytree(synth_seq, root)
    (root / "depth" / "000012.png").write_bytes(b"not a png")
    cfg = TrackerConfig()
    cfg.sdf = replace(cfg.sdf, enabled=False)
    with pytest.raises(SequenceError, match=rf"^{root / 'depth' / '000012.png'}: unreadable image"):
        track_sequence(open_sequence(root), tmp_path / "out", cfg)
    assert sorted(read_poses(tmp_path / "out" / "ob_in_cam")) == [f"{i:06d}" for i in range(12)]


def test_frames_observed_ahead_give_the_poses_of_frames_observed_in_line(synth_seq, tmp_path):
    """`track_sequence` preprocesses a frame that comes with its mask, and finds its features, in the reader's
    thread while the frame before is tracked (`SurgTracker.observe`); the poses are those of a tracker that does it
    all itself, frame by frame. An observation passed with another frame is refused."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf = replace(cfg.sdf, enabled=False)
    track_sequence(seq, tmp_path / "out", cfg)
    ahead = {p.stem: p.read_text() for p in (tmp_path / "out" / "ob_in_cam").glob("*.txt")}
    tracker = SurgTracker(cfg)
    in_line = {seq[0].id: format_pose(tracker.register(seq[0], seq[0].mask))}
    for frame in list(seq)[1:]:
        result = tracker.track(frame, frame.mask)
        if result.pose is not None:
            in_line[frame.id] = format_pose(result.pose)
    assert len(in_line) >= 25 and ahead == in_line
    frame, other = seq[3], seq[4]
    assert tracker.observe(replace(frame, mask=None)) is None
    with pytest.raises(ValueError, match="another frame"):
        tracker.track(frame, frame.mask, tracker.observe(other))


def test_no_graph_ablation_uses_ransac_only(synth_seq, tmp_path):
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.graph = replace(cfg.graph, enabled=False)
    cfg.sdf = replace(cfg.sdf, enabled=False)
    summary = track_sequence(seq, tmp_path / "out", cfg)
    records = [json.loads(x) for x in (tmp_path / "out" / "track.jsonl").read_text().splitlines()]
    assert all("graph" not in r["ms"] for r in records)
    assert summary.frames == len(seq)


def test_preprocess_points_lie_on_their_pixels_rays(synth_seq):
    """The instrument crop is lifted with its offset in the image: each point is its pixel's ray at its depth."""
    from surgtrack.config import PreprocessConfig
    from surgtrack.preprocess import preprocess

    frame = open_sequence(synth_seq)[5]
    obs = preprocess(frame, frame.mask, PreprocessConfig())
    assert obs.n_valid > 300
    np.testing.assert_allclose(obs.xyz[obs.valid], depth_to_xyz(obs.depth, frame.K)[obs.valid], atol=1e-6)


def test_a_field_that_disagrees_with_the_frame_stays_out_of_the_graph(synth_seq):
    """With sdf.agree_tol set, L_SDF joins only while the field fits the frame at its coarse pose."""
    from scipy.spatial import cKDTree

    from surgtrack.geometry import inv_T, transform

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.sdf.agree_tol = 0.003
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    node = tracker.recent[-1]
    surface = cKDTree(transform(inv_T(node.pose), node.xyz[node.xyz[..., 2] > 0]))
    tracker.sdf = lambda p: (surface.query(p)[0], np.zeros_like(p))  # |Psi| = distance to the frame's surface
    assert tracker._field_agrees(node)
    tracker.sdf = lambda p: (surface.query(p + [0.02, 0.0, 0.0])[0], np.zeros_like(p))  # the same, 2 cm off
    assert not tracker._field_agrees(node)
    cfg.sdf.agree_tol = 0.0
    assert tracker._field_agrees(node)  # off: a converged field always joins


def test_each_frame_says_whether_the_field_was_in_its_graph(synth_seq, tmp_path):
    """track.jsonl and summary.json tell which poses had L_SDF (eq. 11) in their graph: none before there is a field,
    the frames after one fitting the instrument joins, none while the field disagrees with the frames, and none with
    the term's weight graph.w_s at 0."""
    from scipy.spatial import cKDTree

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    tracker = SurgTracker(cfg)

    def field_at(frame, result) -> None:
        if frame.index == 9:  # |Psi| = distance to the model's points: a field that fits the instrument
            tree = cKDTree(tracker.model_points)
            tracker.sdf = lambda p: (tree.query(p)[0], np.zeros_like(p))
        if frame.index == 19:  # the same 2 cm off
            tree = cKDTree(tracker.model_points + [0.02, 0.0, 0.0])
            tracker.sdf = lambda p: (tree.query(p)[0], np.zeros_like(p))

    summary = track_sequence(seq, tmp_path / "out", cfg, on_frame=field_at, tracker=tracker)
    joined = [json.loads(x)["sdf"] for x in (tmp_path / "out" / "track.jsonl").read_text().splitlines()]
    assert not any(joined[:10]) and not any(joined[20:])
    assert sum(joined[10:20]) >= 8
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["sdf_frames"] == summary.sdf_frames == sum(joined)
    assert saved["sdf_from"] == summary.sdf_from == joined.index(True)
    cfg.graph.w_s = 0.0  # the term weighs nothing: it is not in the graph
    tracker = SurgTracker(cfg)
    assert track_sequence(seq, tmp_path / "w_s0", cfg, on_frame=field_at, tracker=tracker).sdf_frames == 0


def test_the_run_summary_counts_frames_and_averages_the_tracked_frames_stage_times():
    """`track` and `live` print and save these counts: the registered first frame is a frame but has no stages."""
    summary = RunSummary()
    summary.add(0, TrackResult(np.eye(4), TRACKED, 1.0))
    summary.add(1, TrackResult(np.eye(4), TRACKED, 0.9, {"graph": 0.010}, sdf=True))
    summary.add(2, TrackResult(None, LOST, 0.0, {"graph": 0.030}, reason=HIDDEN))
    turns = (Unmeasured("turn", np.array([1.0, 0, 0])), Unmeasured("turn", np.array([0, 1.0, 0])))
    summary.add(3, TrackResult(np.eye(4), RELOCALISED, 0.8, {"graph": 0.020, "ransac": 0.006}, sdf=True,
                               unmeasured=turns))
    assert (summary.frames, summary.lost, summary.relocalised) == (4, 1, 1)
    assert (summary.sdf_frames, summary.sdf_from) == (2, 1)
    assert summary.stage_ms == pytest.approx({"graph": 20.0, "ransac": 2.0})
    summary.seconds = 2.0
    assert summary.line() == ("4 frames, 1 lost (1 hidden), 1 relocalised, turn unmeasured on 1, L_SDF from frame 1 "
                              "on 2, 2.0 frames/s (graph 20.0, ransac 2.0 ms)")
    assert summary.to_dict()["stage_ms"] == {"graph": 20.0, "ransac": 2.0}
    assert summary.to_dict()["lost_because"] == {HIDDEN: 1}
    assert summary.to_dict()["unmeasured"] == {"turn": 1}  # frames, not directions


def test_the_end_of_run_mesh_is_the_final_field_kept_to_what_was_seen(synth_seq):
    """The end-of-run mesh refits the field on every keyframe; the rays gathered for it (about 1 MB a keyframe)
    are not kept after it. The mesh is that field's surface within ``sdf.mesh_seen`` voxels of the model points,
    pieces under ``sdf.mesh_floater`` of the largest's seen area dropped."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.background = False
    tracker = tracked(seq, cfg, 8)
    assert tracker._field._rays  # the in-line refits keep their views' rays
    mesh = tracker.mesh()
    assert mesh is not None and len(mesh.faces) > 0
    psi = tracker.fitted_field()
    assert psi is tracker._field and not psi._rays
    assert tracker.surface(psi).area == pytest.approx(mesh.area)
    tracker.cfg.sdf.mesh_seen = 20.0  # the closed surface round what no keyframe saw comes back
    assert tracker.surface(psi).area > 1.2 * mesh.area
    tracker.cfg.sdf.mesh_floater = 1.0  # the piece with the most seen area only
    assert trimesh.graph.connected_component_labels(tracker.surface(psi).face_adjacency).max() == 0


def test_keyframe_poses_refined_with_the_field_stay_within_bounds(synth_seq, tmp_path):
    """sdf.refine_poses: the keyframes take the poses fitted jointly with Psi, the first fixed, each within the
    bound of its tracked pose, and tracking stays as accurate."""
    from surgtrack.geometry import inv_T, rotation_angle_deg

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.background = False
    cfg.sdf.refine_poses = True
    tracker = SurgTracker(cfg)
    track_sequence(seq, tmp_path / "out", cfg, tracker=tracker)
    kfs = tracker.pool.keyframes
    assert len(kfs) >= 4
    np.testing.assert_array_equal(kfs[0].pose, kfs[0].tracked_pose)
    moved = 0
    for kf in kfs[1:]:
        step = inv_T(kf.tracked_pose) @ kf.pose
        assert np.linalg.norm(step[:3, 3]) <= np.sqrt(3) * cfg.sdf.refine_trans + 1e-9
        assert rotation_angle_deg(step[:3, :3]) <= np.sqrt(3) * cfg.sdf.refine_rot_deg + 1e-6
        moved += not np.allclose(kf.pose, kf.tracked_pose)
    assert moved == len(kfs) - 1
    m = evaluate(tmp_path / "out", seq)
    assert m["add_s_auc"] >= 85 and m["add_auc"] >= 70, (m["add_s_auc"], m["add_auc"])


def test_tracks_from_the_first_mask_only(synth_seq, tmp_path):
    """Without masks after the first, each frame is masked by the model at the predicted pose, then again at the
    tracked one: the keyframes' masks match the true masks and the poses stay accurate."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.background = False
    tracker = SurgTracker(cfg)
    track_sequence(seq, tmp_path / "out", cfg, first_mask_only=True, tracker=tracker)
    m = evaluate(tmp_path / "out", seq)
    assert m["add_s_auc"] >= 85 and m["add_auc"] >= 70, (m["add_s_auc"], m["add_auc"])
    truth = {f.id: f.mask & (f.depth > 0) for f in seq}
    iou = [(k.mask & truth[k.frame_id]).sum() / (k.mask | truth[k.frame_id]).sum() for k in tracker.pool.keyframes[1:]]
    assert min(iou) > 0.78 and np.mean(iou) > 0.87, iou  # not masked again: mean 0.85
    lines = [json.loads(x) for x in (tmp_path / "out" / "track.jsonl").read_text().splitlines()]
    assert "colour" not in lines[0]  # the first frame's mask is given
    assert all(("colour" in x) == (x["status"] != LOST) for x in lines[1:])


def test_without_masks_each_posed_frame_says_how_much_its_made_mask_looks_like_the_instrument(synth_seq):
    """`TrackResult.colour`: the mean colour posterior of the mask the tracker made, high while it holds the
    instrument; the same frame with the mask's pixels painted in the first frame's surroundings' colours (a hand
    the model grew into looks so) is still posed, on its depth, but says so. A frame with its mask says nothing.
    The colour gates of the made mask, which would take such pixels out, are off: a glove's colours pass them."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.preprocess.predicted_mask_colour = cfg.preprocess.predicted_mask_colour_inside = 0.0
    tracker = tracked(seq, cfg, 5)
    assert tracker.track(seq[5], seq[5].mask).colour is None
    made = tracker.track(seq[6])
    assert made.pose is not None and made.colour > 0.7, made.colour
    frame = seq[6]
    ring = tracker.colour._ring(seq[0].mask) & (seq[0].depth > 0)
    surroundings = np.median(seq[0].rgb[ring], axis=0).astype(np.uint8)
    painted = replace(frame, rgb=np.where(frame.mask[..., None], surroundings, frame.rgb))
    tracker = tracked(seq, cfg, 6)
    hidden = tracker.track(painted)
    assert hidden.pose is not None and hidden.colour < 0.3, hidden.colour


def test_a_frame_with_its_mask_takes_fewer_gauss_newton_steps(synth_seq, monkeypatch):
    """A frame that came with its mask is solved in ``graph.given_mask_iterations`` steps, one whose mask was
    predicted in ``graph.iterations``: its mask is made again at the pose the steps reach."""
    import surgtrack.tracker as tracker_module

    steps: list[int] = []
    solve = tracker_module.optimize_graph

    def counted(nodes, edges, cfg, *args, **kwargs):
        steps.append(cfg.iterations)
        return solve(nodes, edges, cfg, *args, **kwargs)

    monkeypatch.setattr(tracker_module, "optimize_graph", counted)
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.graph.iterations, cfg.graph.given_mask_iterations = 5, 2
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    steps.clear()
    assert tracker.track(seq[1], seq[1].mask).status == "tracked"
    assert steps and set(steps) == {2}, steps
    steps.clear()
    assert tracker.track(seq[2], None).status == "tracked"
    assert steps and set(steps) == {5}, steps


@pytest.mark.parametrize("min_area", [0.5, 0.0])
def test_a_mostly_hidden_instrument_without_its_mask_does_not_become_a_keyframe(synth_seq, min_area):
    """Tracked without a mask, a frame whose predicted mask covers less than ``pool.min_predicted_area`` of the
    largest keyframe mask (here half; part of the instrument is behind a hand) is tracked but not added to the
    memory pool: a mostly hidden instrument's mask is mostly the margin around the model, and what lies there at the
    instrument's depth would join the model. The next frame, which shows the instrument, is added as before."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.pool.keyframe_rot_deg = 0.0  # every tracked frame is a new view
    cfg.pool.min_predicted_area = min_area
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    frame = seq[1]
    v, u = np.nonzero(frame.mask & (frame.depth > 0))
    hidden = np.argsort(u)[: int(0.4 * len(u))]  # the leftmost 40 % of its pixels, behind a hand
    rgb, depth = frame.rgb.copy(), frame.depth.copy()
    rgb[v[hidden], u[hidden]] = (200, 160, 140)
    depth[v[hidden], u[hidden]] -= 0.05
    assert tracker.track(replace(frame, rgb=rgb, depth=depth), None).status == "tracked"
    assert len(tracker.pool) == (2 if min_area == 0 else 1)
    assert tracker.track(seq[2], None).status == "tracked"
    assert len(tracker.pool) == (3 if min_area == 0 else 2)


@pytest.mark.parametrize("wide", [12, 0])
def test_without_masks_an_instrument_that_moved_beyond_the_margin_is_masked_again_wider(synth_seq, wide):
    """Tracked without a mask, a frame whose mask made at the last pose (its 4-pixel margin) holds too few trusted
    points, because the instrument moved further since (a fast hand; here four frames dropped, 2.4 cm), is masked
    again with ``preprocess.predicted_mask_wide_margin`` pixels and tracked; with 0 it is lost."""
    from surgtrack.metrics import add_errors, model_points

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.preprocess.predicted_mask_wide_margin = wide
    tracker = SurgTracker(cfg)
    first = tracker.register(seq[0], seq[0].mask)
    for i in range(1, 6):
        assert tracker.track(seq[i], None).status == TRACKED
    result = tracker.track(seq[10], None)
    if wide == 0:
        assert result.status == LOST and result.reason == HIDDEN
        return
    gt = seq.gt_poses()
    to_truth = np.linalg.inv(first) @ gt[seq.ids[0]]  # the tracker's object frame -> the ground truth's
    moved = np.linalg.norm(gt[seq.ids[10]][:3, 3] - gt[seq.ids[5]][:3, 3])
    points = model_points(seq.gt_visible_points(), seq.gt_model())
    error = add_errors([result.pose @ to_truth], [gt[seq.ids[10]]], points)[0]
    assert result.status == TRACKED and moved > 0.02 and error < 0.01, (moved, error)


@pytest.mark.parametrize("case", ["joins", "moved on", "off"])
def test_without_masks_a_keyframe_in_new_colours_joins_once_a_later_frame_sees_it_again(synth_seq, case):
    """Tracked without a mask, a frame whose made mask's colour is under ``pool.keyframe_colour`` of the first ten
    tracked frames' (here the instrument shows a colour the first frame never did: a handle, or a glove round it)
    does not join the memory pool at once. ``pool.probation_frames`` later, a tracked frame that sees the points it
    adds to the model where they were lets it join (the first mask showed three quarters of the instrument, this
    frame's wider mask the rest; the frames' depth lies on the instrument only); one that sees past them (what the
    mask took in has moved on: the frame sees the table behind) does not. ``pool.keyframe_colour`` 0: it joins at
    once."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.pool.keyframe_rot_deg = 90.0  # no keyframes until the painted frame: the model stays what the first showed
    cfg.pool.probation_frames = 3
    cfg.pool.keyframe_colour = 0.0 if case == "off" else 0.85
    first = seq[0].mask.copy()
    v, u = np.nonzero(first & (seq[0].depth > 0))
    shaft = np.linalg.eigh(np.cov(np.stack([u, v])))[1][:, -1]
    along = (u - u.mean()) * shaft[0] + (v - v.mean()) * shaft[1]
    far = along > np.quantile(along, 0.75)
    first[v[far], u[far]] = False
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], first)
    for i in range(1, 11):
        assert tracker.track(seq[i], None).status == TRACKED

    def instrument_only(frame, rgb=None):  # the frame's depth on the instrument only: no hand or table beside it
        return replace(frame, rgb=frame.rgb if rgb is None else rgb, depth=np.where(frame.mask, frame.depth, 0))

    later = instrument_only if case == "joins" else (lambda f: f)

    frame = seq[11]
    painted = frame.rgb.copy()
    painted[frame.mask] = (255, 0, 255)
    cfg.pool.keyframe_rot_deg = 0.0
    cfg.preprocess.predicted_mask_margin = 15  # takes in the rest of the instrument
    result = tracker.track(instrument_only(frame, painted), None)
    cfg.pool.keyframe_rot_deg, cfg.preprocess.predicted_mask_margin = 90.0, 4
    assert result.status == TRACKED and result.colour < 0.85 * np.median(tracker.first_colours)
    pooled = lambda: frame.id in [k.frame_id for k in tracker.pool.keyframes]  # noqa: E731
    assert pooled() == (case == "off")
    if case == "moved on":  # what the mask took in lay 10 % nearer the camera, where the next frames see past
        node = tracker._probation[0]
        node.xyz = node.xyz * 0.9
    for i in (12, 13):
        assert tracker.track(later(seq[i]), None).status == TRACKED
        assert pooled() == (case == "off")
    assert tracker.track(later(seq[14]), None).status == TRACKED
    assert pooled() == (case in ("joins", "off"))
    assert tracker._probation is None


@pytest.mark.parametrize("gap", [0.02, 0.0])
def test_without_masks_an_occluder_in_front_of_the_instrument_teaches_the_colour_model(synth_seq, gap):
    """Tracked without a mask, the pixels well in front of the model at the tracked pose (a hand across the
    instrument) join the colour model's surroundings, so the same colour is kept out of later masks beside the
    instrument (``preprocess.colour_occluder_gap``; 0 turns it off)."""
    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.preprocess.colour_occluder_gap = gap
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    glove = np.array([[[150, 60, 200]]], np.uint8)
    assert abs(tracker.colour.posterior(glove)[0, 0] - 0.5) < 0.01  # not seen in the first frame
    for frame in seq[1], seq[2], seq[3]:
        v, u = np.nonzero(frame.mask & (frame.depth > 0))
        across = np.abs(u - np.median(u)) < 10  # a band of the instrument's pixels, covered by a violet glove
        rgb, depth = frame.rgb.copy(), frame.depth.copy()
        rgb[v[across], u[across]] = glove
        depth[v[across], u[across]] -= 0.05
        assert tracker.track(replace(frame, rgb=rgb, depth=depth), None).status == "tracked"
    learnt = tracker.colour.posterior(glove)[0, 0] < cfg.preprocess.predicted_mask_colour
    assert learnt == (gap > 0)


def test_a_pose_slid_along_the_shaft_loses_to_the_prediction_the_model_fits(synth_seq):
    """A tracked pose that departs from the constant-velocity prediction by more than ransac.check_jump_trans (a
    few feature matches between a shaft's repeated markings) is checked: the refined prediction wins when the
    model fits it better, as it does where the shaft's end no longer meets the model's."""
    from surgtrack.preprocess import preprocess

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    tracker = tracked(seq, cfg, 6)
    truth = tracker.track(seq[6], seq[6].mask).pose
    tracker.recent.pop()  # frame 6 again, from frame 5
    obs = preprocess(seq[6], seq[6].mask, cfg.preprocess)
    feats = tracker.extractor(obs)
    pts = tracker.model_points
    axis = np.linalg.svd(pts - pts.mean(axis=0), full_matrices=False)[2][0]  # the shaft, in the object frame
    slid = tracker._node(obs, feats, truth @ make_T(np.eye(3), 0.04 * axis))
    steady = tracker._checked_jump(obs, feats, slid)
    assert steady is not slid
    assert np.linalg.norm(steady.pose[:3, 3] - truth[:3, 3]) < 0.005
    near = tracker._node(obs, feats, truth @ make_T(np.eye(3), 0.005 * axis))
    assert tracker._checked_jump(obs, feats, near) is near  # within the check's bound: taken as it is
    cfg.ransac.check_jump_fit = 0.01  # the prediction must fit a hundred times better: the slid node is kept
    optimise = tracker._optimise
    tracker._optimise = lambda *a, **k: tracker.rng.random() and optimise(*a, **k)  # its refinement draws
    drawn = tracker.rng.bit_generator.state
    assert tracker._checked_jump(obs, feats, slid) is slid
    assert tracker.rng.bit_generator.state == drawn  # and the run's random draws are as they were
    cfg.ransac.check_jump_fit = 0.0
    assert tracker._checked_jump(obs, feats, slid) is slid  # the check off


def test_a_frames_fit_to_the_model_follows_its_pose_and_the_model(synth_seq):
    """The confidence (the share of a frame's points near the model) is worked out once for a node's pose and kept;
    it is found again when the pose moves, even in place, and when the model grows."""
    from scipy.spatial import cKDTree

    from surgtrack.preprocess import preprocess

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    tracker = tracked(seq, cfg, 6)
    obs = preprocess(seq[6], seq[6].mask, cfg.preprocess)
    node = tracker._node(obs, tracker.extractor(obs), tracker.recent[-1].pose.copy())
    at = tracker._confidence(node)
    assert at > 0.9
    node.pose[:3, 3] += [0.0, 0.1, 0.0]  # 10 cm off, moved in place
    assert tracker._confidence(node) < 0.2
    node.pose[:3, 3] -= [0.0, 0.1, 0.0]
    assert tracker._confidence(node) == at
    tracker._model_tree = cKDTree(tracker.model_points + [0.1, 0.0, 0.0])  # a model elsewhere
    assert tracker._confidence(node) < 0.2


def test_free_space_acts_on_frames_that_came_with_their_mask(synth_seq, monkeypatch):
    """L_FS (graph.w_fs) refines the pose of a frame given with its mask against that mask. A frame without one is
    masked from the model's prediction, whose surroundings are not known to be free: it gets L_FS against the
    background only (graph.free_space_background: the pixels whose depth lies that far behind the model), for the
    points the given masks made, unless graph.free_space_predicted trusts the predicted mask; with neither, none."""
    import surgtrack.tracker as tracker_module

    seq = open_sequence(synth_seq)
    seen = []
    graph = tracker_module.optimize_graph
    monkeypatch.setattr(tracker_module, "optimize_graph",
                        lambda *a, **k: seen.append(k.get("free_space")) or graph(*a, **k))
    for predicted_too, background in ((False, 0.0), (False, 0.05), (True, 0.05)):
        cfg = TrackerConfig()
        cfg.sdf.enabled = False
        cfg.graph.free_space_predicted = predicted_too
        cfg.graph.free_space_background = background
        tracker = SurgTracker(cfg)
        tracker.register(seq[0], seq[0].mask)
        seen.clear()
        assert tracker.track(seq[1], seq[1].mask).status == "tracked"
        assert seen and all(fs is not None and fs[0] == 0 for fs in seen)
        assert all(len(fs[1].points) == min(len(tracker.model_points), cfg.graph.free_space_points) for fs in seen)
        given = {tuple(p) for p in tracker.model_points[tracker._given]}
        pose, far = tracker.recent[-1].pose, tracker.model_points + [5.0, 0.0, 0.0]  # out of view
        tracker._remember_points(SimpleNamespace(pose=pose, xyz=transform(pose, far)[:, None]), given=False)
        seen.clear()
        assert tracker.track(seq[2], None).status == "tracked"
        assert seen and all((fs is not None) == (predicted_too or background > 0) for fs in seen)
        if background > 0 and not predicted_too:
            depth = seq[2].depth
            for _, fs in seen:
                assert all(tuple(p) in given for p in fs.points)  # the given mask's points only
                outline = fs.view.edge.mask
                assert not outline[depth > 0.9].any()  # the drape, 0.5 m or more behind the instrument
                assert outline[(depth > 0) & (depth < 0.5)].all()  # the instrument, the hand: not known free
    cfg.graph.w_fs = 0.0
    seen.clear()
    tracker.track(seq[3], seq[3].mask)
    assert seen and all(fs is None for fs in seen)


def test_coverage_looks_into_the_first_keyframe_on_frames_that_came_with_their_mask(synth_seq, monkeypatch):
    """L_CV (graph.w_cv) refines the pose of a frame given with its mask against what the first keyframe saw past;
    a frame masked from the model's prediction, one that shows less than
    graph.coverage_min_share of the first keyframe's points, and w_cv 0 go without it."""
    import surgtrack.tracker as tracker_module

    seq = open_sequence(synth_seq)
    seen = []
    graph = tracker_module.optimize_graph
    monkeypatch.setattr(tracker_module, "optimize_graph",
                        lambda *a, **k: seen.append(k.get("coverage")) or graph(*a, **k))
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    first = tracker.pool.keyframes[0]
    assert tracker.track(seq[1], seq[1].mask).status == "tracked"
    assert seen and all(cv is not None and cv[0] == 0 for cv in seen)
    cv = seen[-1][1]
    assert cv.view is first.view and np.allclose(cv.C_view @ first.pose, np.eye(4))
    seen.clear()
    assert tracker.track(seq[2], None).status == "tracked"
    assert seen and all(cv is None for cv in seen)
    for setting, value in (("coverage_min_share", 10.0), ("w_cv", 0.0)):
        tracker.cfg.graph = replace(cfg.graph, **{setting: value})
        seen.clear()
        tracker.track(seq[3], seq[3].mask)
        assert seen and all(cv is None for cv in seen)


def test_the_field_is_refitted_as_keyframes_arrive_after_the_pool_is_full(synth_seq, monkeypatch):
    """sdf.refit_every counts the keyframes added, not the pool's size: a full pool stays full as keyframes come
    and go, and the field must still be refitted on them."""
    from surgtrack.memory_pool import MemoryPool
    from surgtrack.registration import InstrumentSDF

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.background = False
    cfg.sdf.iterations, cfg.sdf.refit_iterations, cfg.sdf.refit_every = 4, 2, 2
    cfg.pool.max_size, cfg.pool.keyframe_rot_deg = 3, 0.5
    added, refits = [], []  # keyframe ids; the number of keyframes added at each refit
    add, refit = MemoryPool.add, InstrumentSDF.refit

    def counted_add(pool, kf):
        added.append(kf.frame_id)
        add(pool, kf)

    def counted_refit(psi, *args, **kwargs):
        refits.append(len(added))
        return refit(psi, *args, **kwargs)

    monkeypatch.setattr(MemoryPool, "add", counted_add)
    monkeypatch.setattr(InstrumentSDF, "refit", counted_refit)
    tracker = tracked(seq, cfg, 12)
    assert len(added) >= 8 and len(tracker.pool) == 3
    assert refits == list(range(1, len(added) + 1, 2))  # keyframes 1, 3, 5, ...: on after the pool filled


def test_the_background_fit_starts_once_the_pool_holds_its_first_views(synth_seq, monkeypatch):
    """A background first fit on one keyframe would come back after the pool holds dozens: the first request
    waits for ``sdf.min_first_views`` keyframes; later ones follow every ``sdf.refit_every`` keyframes."""
    from surgtrack.registration import BackgroundFitter

    seq = open_sequence(synth_seq)
    cfg = TrackerConfig()
    cfg.sdf.min_first_views, cfg.sdf.refit_every = 4, 3
    cfg.pool.keyframe_rot_deg = 0.5
    sent = []
    monkeypatch.setattr(BackgroundFitter, "submit", lambda fitter, views: sent.append(len(views)))
    tracker = tracked(seq, cfg, 10)
    assert len(tracker.pool) >= 7
    assert sent[:2] == [4, 7]
    tracker.fitter.close()
