"""Baseline trackers behind the SurgTracker API: accuracy on the rendered sequence, lost frames, the fused mesh."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from surgtrack.baselines import (
    BaselineTracker,
    FrameToFrameICPTracker,
    KinectFusionTracker,
    RansacOnlyTracker,
)
from surgtrack.bench import METHODS, make_tracker
from surgtrack.geometry import backproject, inv_T, make_T, so3_exp, transform
from surgtrack.global_registration import icp
from surgtrack.io import open_sequence, read_poses
from surgtrack.metrics import chamfer_cm, evaluate
from surgtrack.pipeline import track_sequence
from surgtrack.tracker import LOST, SurgTracker, object_origin

BASELINES = ("kinectfusion", "icp", "ransac-only")
# Floors on the 30-frame synth_seq fixture, somewhat below what was measured there with per-frame masks
# (ADD-S / ADD AUC: kinectfusion 97.0 / 95.6, icp 98.5 / 97.0, ransac-only 94.0 / 91.2).
FLOORS = {"kinectfusion": (90, 85), "icp": (90, 85), "ransac-only": (85, 80)}


@pytest.fixture(scope="module")
def runs(synth_seq, tmp_path_factory) -> dict:
    """Each baseline run once over the fixture with per-frame masks: (tracker, summary, metrics)."""
    seq = open_sequence(synth_seq)
    out = {}
    for name in BASELINES:
        tracker = make_tracker(name)
        folder = tmp_path_factory.mktemp(name)
        summary = track_sequence(seq, folder, tracker.cfg, tracker=tracker)
        out[name] = (tracker, summary, evaluate(folder, seq), folder)
    return out


def test_bench_knows_the_baselines():
    assert set(BASELINES) <= set(METHODS)
    assert isinstance(make_tracker("kinectfusion"), KinectFusionTracker)
    assert isinstance(make_tracker("icp"), FrameToFrameICPTracker)
    assert isinstance(make_tracker("ransac-only"), RansacOnlyTracker)
    assert isinstance(make_tracker("surgtrack"), SurgTracker)
    with pytest.raises(ValueError, match="unknown"):
        make_tracker("nope")


@pytest.mark.parametrize("name", BASELINES)
def test_baseline_tracks_the_sequence(runs, synth_seq, name):
    tracker, summary, m, folder = runs[name]
    seq = open_sequence(synth_seq)
    assert summary.frames == len(seq)
    assert summary.lost <= 2
    assert len(read_poses(folder / "ob_in_cam")) == len(seq) - summary.lost
    add_s_floor, add_floor = FLOORS[name]
    assert m["add_s_auc"] >= add_s_floor, m["add_s_auc"]
    assert m["add_auc"] >= add_floor, m["add_auc"]
    assert tracker.model_points is not None and len(tracker.model_points) > 100


@pytest.mark.parametrize("name", ["kinectfusion", "icp"])
def test_depth_baselines_track_from_the_first_mask_only(synth_seq, tmp_path, name):
    """Masks predicted from the model at the last pose (measured ADD-S: kinectfusion 97.9, icp 97.0)."""
    seq = open_sequence(synth_seq)
    tracker = make_tracker(name)
    summary = track_sequence(seq, tmp_path, tracker.cfg, first_mask_only=True, tracker=tracker)
    m = evaluate(tmp_path, seq)
    assert summary.lost <= 2
    assert m["add_s_auc"] >= 85, m["add_s_auc"]


@pytest.mark.parametrize("name", BASELINES)
def test_empty_mask_frame_is_lost_then_found_again(synth_seq, name):
    seq = open_sequence(synth_seq)
    tracker = make_tracker(name)
    assert isinstance(tracker, BaselineTracker)
    pose = tracker.register(seq[0], seq[0].mask)
    pts, _ = backproject(seq[0].depth, seq[0].K, seq[0].mask)
    np.testing.assert_allclose(pose, make_T(np.eye(3), object_origin(pts)))  # SurgTracker's object frame
    result = tracker.track(seq[1], np.zeros_like(seq[1].mask))
    assert result.status == LOST and result.pose is None
    again = tracker.track(seq[2], seq[2].mask)
    assert again.status == "relocalised" and again.pose is not None


def test_register_rejects_a_mask_without_depth(synth_seq):
    frame = open_sequence(synth_seq)[0]
    with pytest.raises(ValueError, match="instrument pixels"):
        KinectFusionTracker().register(frame, np.zeros_like(frame.mask))


def test_kinectfusion_mesh_lies_on_the_seen_surface(runs, synth_seq):
    """The fused mesh lies on the ground-truth surface the video shows (measured: CD 0.19 cm after the protocol's
    ICP, 0.40 cm with the first poses alone, every vertex within 9 mm of a ground-truth point)."""
    tracker, _, m, folder = runs["kinectfusion"]
    seq = open_sequence(synth_seq)
    mesh = tracker.mesh()
    assert mesh is not None and len(mesh.faces) > 100
    assert (folder / "mesh.ply").is_file()
    assert m["cd_cm"] < 0.4, m["cd_cm"]
    first = seq.ids[0]
    to_gt = inv_T(seq.gt_poses()[first]) @ read_poses(folder / "ob_in_cam")[first]
    visible = seq.gt_visible_points()
    assert chamfer_cm(mesh, to_gt, visible, icp=False) < 0.6
    d, _ = cKDTree(visible).query(transform(to_gt, np.asarray(mesh.vertices)))
    assert np.percentile(d, 99) < 0.015  # nothing fused from the background or the hand


def test_icp_recovers_a_small_rigid_motion():
    """A curved, asymmetric patch 50 cm from the camera, moved by 5 degrees and 1 cm, is aligned back to 0.5 mm."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.04, 0.04, (3000, 2))
    z = 0.5 + 4 * xy[:, 0] ** 2 + 2 * xy[:, 1] ** 2 + 3 * xy[:, 0] * xy[:, 1] + 30 * xy[:, 0] ** 3
    target = np.column_stack([xy, z])
    dz_dx = 8 * xy[:, 0] + 3 * xy[:, 1] + 90 * xy[:, 0] ** 2
    dz_dy = 4 * xy[:, 1] + 3 * xy[:, 0]
    normals = np.column_stack([dz_dx, dz_dy, -np.ones(len(xy))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    motion = make_T(so3_exp(np.radians(5) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])),
                    [0.01, -0.004, 0.003])
    source = transform(inv_T(motion), target)
    T, fitness = icp(source, target, np.eye(4), (0.02, 0.01, 0.005), normals)
    assert fitness > 0.95
    assert np.abs(transform(T, source) - target).max() < 5e-4
