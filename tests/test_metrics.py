"""ADD, ADD-S, AUC and Chamfer distance on cases whose answer is known by hand (DESIGN.md section 4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from helpers import write_result

from surgtrack.geometry import make_T, so3_exp
from surgtrack.io import SequenceError, SequenceWriter, open_sequence
from surgtrack.metrics import (
    add_errors,
    adds_errors,
    align_first_frame,
    alignment_anchor,
    auc,
    chamfer,
    chamfer_cm,
    evaluate,
    icp_point_to_point,
    model_points,
    sample_mesh,
)

K = np.array([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])


def gt_trajectory(n: int) -> list[np.ndarray]:
    """An instrument turning and sliding in front of the camera, 0.5 m away."""
    return [make_T(so3_exp(np.array([0.05, 0.1, 0.03]) * t), [0.01 * t, -0.005 * t, 0.5]) for t in range(n)]


def write_sequence(root: Path, poses: list[np.ndarray], mesh: trimesh.Trimesh, visible: np.ndarray | None = None):
    """A tiny sequence in the DESIGN layout: flat synthetic frames, the given gt poses and gt model."""
    w = SequenceWriter(root, K)
    rng = np.random.default_rng(1)
    mask = np.zeros((24, 32), bool)
    mask[8:16, 10:22] = True
    for i, T in enumerate(poses):
        rgb = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
        w.write_frame(i, rgb, np.full((24, 32), 0.5), mask if i == 0 else None, T)
    w.write_model(mesh, visible)
    return open_sequence(root)


def rot_z(deg: float) -> np.ndarray:
    return make_T(so3_exp(np.array([0.0, 0.0, np.radians(deg)])), np.zeros(3))


def shift(x: float, y: float = 0.0, z: float = 0.0) -> np.ndarray:
    return make_T(np.eye(3), [x, y, z])


# ------------------------------------------------------------------------------------------------ AUC


def test_auc_of_a_constant_5mm_error_is_the_hand_value():
    # x = [0, 0.005 (x10), 0.1], y = [0, 0.1, ..., 1.0, 1.0]: x changes at 0.005 (y = 1/10) and at 0.1 (y = 1),
    # so AUC = (0.005 * 0.1 + 0.095 * 1.0) / 0.1 = 95.5 %.
    assert auc([0.005] * 10) == pytest.approx(95.5, abs=1e-9)
    assert auc([0.005] * 4) == pytest.approx(95.0 + 5.0 / 4, abs=1e-9)


def test_auc_limits():
    assert auc([0.0] * 7) == pytest.approx(100.0)
    assert auc([0.1, 0.2, np.inf]) == 0.0  # nothing strictly below 0.1 m
    assert auc([]) == 0.0
    # Half the frames at 2 cm, half at 6 cm: (0.02 * 0.5 + 0.04 * 1.0 ... ) by the formula:
    # x = [0, .02, .02, .06, .06, .1], y = [0, .25, .5, .75, 1, 1] -> .02*.25 + .04*.75 + .04*1 = .075 -> 75 %.
    assert auc([0.02, 0.06, 0.02, 0.06]) == pytest.approx(75.0)


def test_a_missing_frame_lowers_the_auc_by_the_hand_value():
    # Ten perfect frames score 100; one of them missing (infinite error) keeps accuracy at 9/10: 90 %.
    assert auc([0.0] * 9 + [np.inf]) == pytest.approx(90.0)
    # Ten 5 mm frames, one missing: x = [0, .005, ..., .1], y = [0, .1, ..., .9, .9] -> (.005*.1 + .095*.9)/.1 = 86 %.
    assert auc([0.005] * 9 + [np.inf]) == pytest.approx(86.0)


# ------------------------------------------------------------------------------------------------ ADD / ADD-S


def test_alignment_maps_a_consistent_object_frame_onto_the_ground_truth():
    gt = {f"{t:06d}": T for t, T in enumerate(gt_trajectory(5))}
    X = make_T(so3_exp(np.array([0.3, -1.2, 2.0])), [0.1, 0.2, -0.3])
    pred = {k: T @ X for k, T in gt.items()}
    aligned = align_first_frame(pred, pred["000000"], gt["000000"])
    for k in gt:
        np.testing.assert_allclose(aligned[k], gt[k], atol=1e-12)


def test_alignment_anchor_falls_back_to_the_first_predicted_frame():
    ids = ["000000", "000001", "000002"]
    gt = dict.fromkeys(ids, np.eye(4))
    assert alignment_anchor(gt, gt, ids) == "000000"
    assert alignment_anchor({"000002": np.eye(4), "000001": np.eye(4)}, gt, ids) == "000001"
    assert alignment_anchor({"000009": np.eye(4)}, gt, ids) is None


def test_add_of_a_constant_offset_is_the_offset():
    pts = np.random.default_rng(0).normal(size=(500, 3)) * 0.05
    gt = gt_trajectory(4)
    pred = [shift(0.003, 0.004) @ T for T in gt]  # 5 mm in the camera frame
    np.testing.assert_allclose(add_errors(pred, gt, pts), 0.005, atol=1e-12)
    adds = adds_errors(pred, gt, pts)
    assert np.all(adds <= 0.005 + 1e-12) and np.all(adds > 0)


def test_missing_prediction_is_an_infinite_error():
    pts = np.random.default_rng(0).normal(size=(100, 3))
    gt = gt_trajectory(3)
    for errors in (add_errors([gt[0], None, gt[2]], gt, pts), adds_errors([gt[0], None, gt[2]], gt, pts)):
        assert np.isinf(errors[1]) and errors[0] == pytest.approx(0.0, abs=1e-12)


def test_cylinder_rotated_about_its_axis_scores_full_adds_but_not_add():
    cylinder = trimesh.creation.cylinder(radius=0.01, height=0.1, sections=64)  # axis z
    pts = sample_mesh(cylinder, 10_000)
    gt = gt_trajectory(10)
    pred = [gt[0]] + [T @ rot_z(90) for T in gt[1:]]  # roll about the shaft axis after the first frame
    pred = list(align_first_frame(dict(enumerate(pred)), pred[0], gt[0]).values())
    adds, add = adds_errors(pred, gt, pts), add_errors(pred, gt, pts)
    assert adds.max() < 0.001  # every rolled point lies on the surface, within the sample spacing
    assert auc(adds) > 99.0
    # Side points move by the chord r * sqrt(2) = 14 mm; the caps' points move less.
    assert 0.008 < add[1:].mean() < 0.0142
    assert auc(add) < 91.0


def test_model_points_prefer_the_seen_surface():
    box = trimesh.creation.box((0.1, 0.02, 0.02))
    visible = sample_mesh(box, 30_000, seed=5)
    visible = visible[visible[:, 0] > 0]
    pts = model_points(visible, box)
    assert pts.shape == (10_000, 3) and np.all(pts[:, 0] > 0)
    np.testing.assert_array_equal(pts, model_points(visible, box))  # fixed seed
    assert model_points(visible[:50], box).shape == (50, 3)
    assert model_points(None, box).shape == (10_000, 3)
    assert model_points(None, None) is None


# ------------------------------------------------------------------------------------------------ Chamfer


def test_chamfer_of_a_mesh_against_its_own_surface_is_about_zero():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    surface = sample_mesh(sphere, 20_000, seed=7)
    # Only the sampling remains: 20,000 points on 314 cm2 are ~1.3 mm apart.
    assert chamfer_cm(sphere, np.eye(4), surface) < 0.07


def test_chamfer_of_a_1cm_inflated_mesh_is_1cm():
    inner = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    outer = trimesh.creation.icosphere(subdivisions=4, radius=0.06)
    # Every outer point is 1 cm from the inner sphere and vice versa; ICP cannot remove a scale change.
    assert chamfer_cm(outer, np.eye(4), sample_mesh(inner, 20_000, seed=7)) == pytest.approx(1.0, abs=0.05)


def test_chamfer_icp_removes_a_1cm_shift():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    surface = sample_mesh(sphere, 20_000, seed=7)
    # Without ICP a sphere shifted by d is |d cos| away on average: d / 2 = 0.5 cm each way.
    assert chamfer_cm(sphere, shift(0.01), surface, icp=False) == pytest.approx(0.5, abs=0.05)
    assert chamfer_cm(sphere, shift(0.01), surface) < 0.12


def test_icp_recovers_a_small_rigid_motion():
    box = trimesh.creation.box((0.08, 0.03, 0.02))
    dst = sample_mesh(box, 5000, seed=1)
    motion = make_T(so3_exp(np.array([0.02, -0.03, 0.05])), [0.004, -0.003, 0.002])
    src = (dst - motion[:3, 3]) @ motion[:3, :3]  # inv(motion) applied: T = motion maps src onto dst
    np.testing.assert_allclose(icp_point_to_point(src, dst), motion, atol=1e-6)
    assert chamfer(src, src) == 0.0


# ------------------------------------------------------------------------------------------------ evaluate


@pytest.fixture
def box_sequence(tmp_path: Path):
    box = trimesh.creation.box((0.12, 0.02, 0.015))
    visible = sample_mesh(box, 20_000, seed=3)  # the camera went all round
    return write_sequence(tmp_path / "seq", gt_trajectory(10), box, visible), box, visible


def test_evaluate_perfect_prediction(box_sequence, tmp_path: Path):
    seq, box, _ = box_sequence
    out = write_result(tmp_path / "out", seq.gt_poses(), box)
    r = evaluate(out, seq)
    assert r["add_auc"] == pytest.approx(100.0, abs=1e-3)
    assert r["add_s_auc"] == pytest.approx(100.0, abs=1e-3)
    assert r["add_auc_full"] == pytest.approx(100.0, abs=1e-3)
    assert r["add_s_auc_full"] == pytest.approx(100.0, abs=1e-3)
    assert r["cd_cm"] < 0.07
    assert r["frames"] == 10 and r["missing"] == 0 and r["anchor"] == "000000"
    assert r["model_points"] == "visible_points"
    assert list(r["errors"]["add"]) == seq.ids


def test_evaluate_prediction_in_another_object_frame(box_sequence, tmp_path: Path):
    seq, box, _ = box_sequence
    X = make_T(so3_exp(np.array([0.4, 0.9, -1.7])), [0.05, -0.02, 0.1])  # x_pred_obj = inv(X) x_gt_obj
    mesh = box.copy().apply_transform(np.linalg.inv(X))  # the reconstruction lives in the predicted frame
    out = write_result(tmp_path / "out", {k: T @ X for k, T in seq.gt_poses().items()}, mesh)
    r = evaluate(out, seq)
    assert r["add_auc"] == pytest.approx(100.0, abs=1e-3)
    assert r["add_s_auc"] == pytest.approx(100.0, abs=1e-3)
    assert r["cd_cm"] < 0.07


def test_evaluate_counts_missing_frames(box_sequence, tmp_path: Path):
    seq, _, _ = box_sequence
    gt = seq.gt_poses()
    out = write_result(tmp_path / "out", {k: T for k, T in gt.items() if k != "000004"})
    r = evaluate(out, seq)
    assert r["missing"] == 1 and r["missing_ids"] == ["000004"]
    assert r["errors"]["add"]["000004"] is None
    assert r["add_auc"] == pytest.approx(90.0, abs=1e-3)
    assert r["cd_cm"] is None


def test_evaluate_counts_frames_given_a_wrong_pose_apart_from_lost_ones(box_sequence, tmp_path: Path):
    """A tracker that gives a pose 20 cm off instead of reporting the frame lost scores the same AUC, but ``wrong``
    tells the two apart: the pose a navigation system would have shown."""
    seq, _, _ = box_sequence
    gt = seq.gt_poses()
    off = {k: (shift(0.2) @ T if k in ("000004", "000005") else T) for k, T in gt.items()}
    lost = {k: T for k, T in gt.items() if k not in ("000004", "000005")}
    r_off = evaluate(write_result(tmp_path / "off", off), seq)
    r_lost = evaluate(write_result(tmp_path / "lost", lost), seq)
    assert r_off["add_auc"] == pytest.approx(r_lost["add_auc"], abs=1e-6)
    assert (r_off["wrong"], r_off["missing"]) == (2, 0)
    assert (r_lost["wrong"], r_lost["missing"]) == (0, 2)


def test_evaluate_without_frame_zero_aligns_on_the_first_predicted_frame(box_sequence, tmp_path: Path):
    seq, _, _ = box_sequence
    X = shift(0.2, 0.1, 0.0)
    out = write_result(tmp_path / "out", {k: T @ X for k, T in seq.gt_poses().items() if k != "000000"})
    r = evaluate(out, seq)
    assert r["anchor"] == "000001" and r["missing_ids"] == ["000000"]
    assert r["add_auc"] == pytest.approx(90.0, abs=1e-3)


def test_evaluate_constant_offset_gives_the_hand_auc(box_sequence, tmp_path: Path):
    seq, _, _ = box_sequence
    gt = seq.gt_poses()
    # Frame 0 exact (it fixes the alignment); every later frame 5 mm off in the camera frame.
    pred = {k: (T if k == "000000" else shift(0.0, 0.005) @ T) for k, T in gt.items()}
    r = evaluate(write_result(tmp_path / "out", pred), seq)
    # errors: one 0 and nine 5 mm -> x changes at 0.005 (y = 2/10, the first non-zero) and at 0.1 (y = 1).
    assert r["add_auc"] == pytest.approx((0.005 * 0.2 + 0.095 * 1.0) / 0.1 * 100, abs=1e-4)
    assert r["add_s_auc"] >= r["add_auc"]


def test_evaluate_rejects_unscorable_input(box_sequence, tmp_path: Path):
    seq, _, _ = box_sequence
    with pytest.raises(SequenceError, match="result folder does not exist"):
        evaluate(tmp_path / "nowhere", seq)
    (tmp_path / "empty").mkdir()
    with pytest.raises(SequenceError, match=r"ob_in_cam: no predicted poses"):
        evaluate(tmp_path / "empty", seq)
    bad = write_result(tmp_path / "scaled", {"000000": np.diag([2.0, 2.0, 2.0, 1.0])})
    with pytest.raises(SequenceError, match=r"000000\.txt: not a rigid transform"):
        evaluate(bad, seq)
    other = write_result(tmp_path / "other", {"123": np.eye(4)})
    with pytest.raises(SequenceError, match="no predicted pose matches a ground-truth frame"):
        evaluate(other, seq)


# ------------------------------------------------------------------------------------------------ figures


def test_accuracy_curve_steps():
    from surgtrack.plots import accuracy_curve

    x, y = accuracy_curve({"0": 0.005, "1": None, "2": 0.2, "3": 0.0, "4": 0.005})
    np.testing.assert_allclose(x, [0.0, 0.0, 0.005, 0.005, 0.1])
    np.testing.assert_allclose(y, [0.2, 0.2, 0.6, 0.6, 0.6])  # the missing frame and the 20 cm one never count


def test_figures_compare_methods(box_sequence, tmp_path: Path):
    import cv2

    from surgtrack.plots import plot_accuracy, plot_errors_over_time, plot_evaluation

    errors = {"surgtrack": [0.001, 0.004, None, 0.02], "icp": {"a": 0.03, "b": 0.2, "c": 0.05, "d": None}}
    for path in (
        plot_accuracy(errors, tmp_path / "acc.png", "ADD"),
        plot_errors_over_time(errors, tmp_path / "time.png", "ADD"),
    ):
        img = cv2.imread(str(path))
        assert img is not None and img.shape[0] > 200 and img.std() > 0
    seq, _, _ = box_sequence
    r = evaluate(write_result(tmp_path / "out", seq.gt_poses()), seq)
    paths = plot_evaluation(r, tmp_path / "out")
    assert [p.name for p in paths] == ["accuracy_add.png", "accuracy_add_s.png", "errors_over_time.png"]
    assert all(p.is_file() for p in paths)
