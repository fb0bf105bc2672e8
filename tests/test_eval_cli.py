"""End to end: ``surgtrack eval OUT SEQ`` on a BOP scene of real RealSense frames and on a generated sequence."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from helpers import assert_one_line_error, surgtrack, surgtrack_here, write_result

from surgtrack.geometry import make_T, so3_exp
from surgtrack.io import SequenceWriter, open_sequence

APC_SCENE = "real/apc_shelf_scene/scene-0000"


def shift(x: float, y: float, z: float) -> np.ndarray:
    return make_T(np.eye(3), [x, y, z])


# ------------------------------------------------------------------------------------------------ real frames, BOP


@pytest.fixture(scope="module")
def bop_scene(shared_data: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict, trimesh.Trimesh]:
    """The real APC RealSense frames rewritten as a BOP scene of object 1 (model: hull of the seen surface, mm)."""
    apc = open_sequence(shared_data / APC_SCENE)
    root = tmp_path_factory.mktemp("bop")
    scene = root / "test" / "000001"
    for sub in ("rgb", "depth", "mask_visib"):
        (scene / sub).mkdir(parents=True)
    gt = apc.gt_poses()
    cams, gts = {}, {}
    for i, f in enumerate(apc):
        n = f"{i:06d}"
        cv2.imwrite(str(scene / "rgb" / f"{n}.png"), cv2.cvtColor(f.rgb, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(scene / "depth" / f"{n}.png"), np.round(f.depth * 1e4).astype(np.uint16))  # 0.1 mm
        mask = np.zeros(f.depth.shape, bool) if f.mask is None else f.mask
        cv2.imwrite(str(scene / "mask_visib" / f"{n}_000000.png"), mask.astype(np.uint8) * 255)
        cams[str(i)] = {"cam_K": f.K.ravel().tolist(), "depth_scale": 0.1}
        T = gt[f.id]
        gts[str(i)] = [{"obj_id": 1, "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": (T[:3, 3] * 1e3).tolist()}]
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    seen = apc.gt_visible_points()
    d = np.linalg.norm(seen - np.median(seen, axis=0), axis=1)
    hull = trimesh.PointCloud(seen[d < np.percentile(d, 99)]).convex_hull  # without the mask-edge stragglers
    (root / "models").mkdir()
    hull.copy().apply_scale(1e3).export(root / "models" / "obj_000001.ply")
    return scene, gt, hull


def test_eval_bop_scene_of_real_frames(bop_scene, tmp_path: Path):
    scene, gt, hull = bop_scene
    ids = sorted(gt)
    # Predicted in another object frame X; frame 0 exact, later frames 5 mm off in the camera frame, 000007 lost.
    X = make_T(so3_exp(np.array([0.2, -0.5, 1.0])), [0.03, 0.01, -0.02])
    pred = {k: (T if k == ids[0] else shift(0.003, 0.0, 0.004) @ T) @ X for k, T in gt.items() if k != "000007"}
    out = write_result(tmp_path / "out", pred, hull.copy().apply_transform(np.linalg.inv(X)))
    run = surgtrack("eval", out, scene, "--obj-id", "1", "--plot")
    assert run.returncode == 0, run.stderr
    assert "ADD AUC" in run.stdout and "Chamfer distance" in run.stdout
    r = json.loads((out / "metrics.json").read_text())
    n = len(ids)
    assert r["frames"] == n == 15 and r["missing"] == 1 and r["missing_ids"] == ["000007"]
    # Sorted errors: 0, thirteen of 5 mm, one missing. x changes at 5 mm (y = 2/n) and at 0.1 m (y = 14/n).
    expected = (0.005 * 2 / n + 0.095 * 14 / n) / 0.1 * 100
    assert r["add_auc"] == pytest.approx(expected, abs=1e-3)
    assert r["add_auc_full"] == pytest.approx(expected, abs=1e-3)  # a pure translation: ADD is the same anywhere
    assert expected <= r["add_s_auc"] <= 100 * 14 / n
    assert r["errors"]["add"]["000003"] == pytest.approx(0.005, abs=1e-6)
    assert r["errors"]["add"]["000007"] is None
    assert r["cd_cm"] < 0.1  # the mesh is the model itself, expressed in the predicted frame
    for png in ("accuracy_add.png", "accuracy_add_s.png", "errors_over_time.png"):
        assert cv2.imread(str(out / png)) is not None


def test_eval_bop_without_the_object(bop_scene, tmp_path: Path):
    scene, gt, _ = bop_scene
    out = write_result(tmp_path / "out", gt)
    assert_one_line_error(surgtrack_here("eval", out, scene, "--obj-id", "4"), "mask_visib", "missing first-frame mask")


# ------------------------------------------------------------------------------------------------ generated sequence


@pytest.fixture
def generated(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray], trimesh.Trimesh]:
    """Eight small frames in the DESIGN layout of a shaft-like box turning in front of the camera."""
    K = np.array([[40.0, 0.0, 16.0], [0.0, 40.0, 12.0], [0.0, 0.0, 1.0]])
    root = tmp_path / "seq"
    w = SequenceWriter(root, K)
    mask = np.zeros((24, 32), bool)
    mask[6:18, 4:28] = True
    poses = {}
    for t in range(8):
        T = make_T(so3_exp(np.array([0.0, 0.08, 0.02]) * t), [0.005 * t, 0.0, 0.45])
        w.write_frame(t, np.full((24, 32, 3), 30 * t, np.uint8), np.full((24, 32), 0.45), mask if t == 0 else None, T)
        poses[f"{t:06d}"] = T
    shaft = trimesh.creation.cylinder(radius=0.004, height=0.2, sections=32)
    seen = trimesh.sample.sample_surface(shaft, 20_000, seed=2)[0]
    w.write_model(shaft, seen[seen[:, 2] < 0.05])  # the camera saw the lower part of the shaft
    return root, poses, shaft


def test_eval_generated_sequence(generated, tmp_path: Path):
    root, poses, shaft = generated
    X = make_T(so3_exp(np.array([1.0, 0.2, 0.0])), [0.0, 0.1, 0.0])
    out = write_result(tmp_path / "out", {k: T @ X for k, T in poses.items()})
    run = surgtrack("eval", out, root)
    assert run.returncode == 0, run.stderr
    r = json.loads((out / "metrics.json").read_text())
    for key in ("add_auc", "add_s_auc", "add_auc_full", "add_s_auc_full"):
        assert r[key] == pytest.approx(100.0, abs=1e-3), key
    assert r["cd_cm"] is None and r["model_points"] == "visible_points"
    assert not (out / "accuracy_add.png").exists()  # figures only with --plot


def test_eval_seen_surface_versus_whole_model(generated, tmp_path: Path):
    root, poses, _ = generated
    # A tilt of 2 degrees about the camera x axis through the seen part: the far end of the shaft swings further.
    tilt = make_T(so3_exp(np.array([np.radians(2.0), 0.0, 0.0])), np.zeros(3))
    pred = {k: (T if k == "000000" else T @ tilt) for k, T in poses.items()}
    out = write_result(tmp_path / "out", pred)
    assert surgtrack("eval", out, root).returncode == 0
    r = json.loads((out / "metrics.json").read_text())
    assert r["add_auc_full"] < r["add_auc"] < 100.0


def test_eval_depth_scale_reaches_the_reader(generated, tmp_path: Path):
    root, poses, _ = generated
    cv2.imwrite(str(root / "depth" / "000000.png"), np.full((24, 32), 4500, np.uint16))  # 0.45 m in 0.1 mm units
    out = write_result(tmp_path / "out", poses)
    run = surgtrack("eval", out, root, "--depth-scale", "0.0001")
    assert run.returncode == 0, run.stderr
    cv2.imwrite(str(root / "depth" / "000000.png"), np.full((24, 32), 2, np.uint16))  # metres as integers
    assert_one_line_error(surgtrack_here("eval", out, root, "--depth-scale", "0.0001"), "000000.png",
                          "units of 0.0001 m")
    assert_one_line_error(surgtrack_here("eval", out, root, "--depth-scale", "0"), "--depth-scale must be positive")


# ------------------------------------------------------------------------------------------------ errors


def test_eval_sequence_without_ground_truth(generated, tmp_path: Path):
    root, poses, _ = generated
    for p in (root / "gt" / "ob_in_cam").iterdir():
        p.unlink()
    out = write_result(tmp_path / "out", poses)
    assert_one_line_error(surgtrack_here("eval", out, root), str(root), "no ground-truth poses")
    assert not (out / "metrics.json").exists()


def test_eval_bad_input_is_one_line(generated, tmp_path: Path):
    root, poses, _ = generated
    assert_one_line_error(surgtrack_here("eval", tmp_path / "missing", root), "result folder does not exist")
    out = write_result(tmp_path / "out", poses)
    (out / "ob_in_cam" / "000002.txt").write_text("1 2 3\n")
    assert_one_line_error(surgtrack_here("eval", out, root), "000002.txt", "expected a 4x4 matrix")
    (root / "cam_K.txt").write_text("1 0\n0 1\n")
    assert_one_line_error(surgtrack_here("eval", out, root), "cam_K.txt", "expected a 3x3 matrix")
