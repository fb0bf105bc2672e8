"""Sequence input and result output (DESIGN.md section 2): every bad input is one error naming file and problem."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

import surgtrack.io as sio
from surgtrack.config import TrackerConfig
from surgtrack.geometry import make_T, so3_exp
from surgtrack.io import (
    BopScene,
    FolderSequence,
    ResultWriter,
    SequenceError,
    SequenceWriter,
    open_sequence,
    read_poses,
    read_track_log,
    sequence_digest,
    write_pose,
)

H, W = 12, 16
K = np.array([[20.0, 0.0, 8.0], [0.0, 20.0, 6.0], [0.0, 0.0, 1.0]])


def pose(t: int) -> np.ndarray:
    return make_T(so3_exp(np.array([0.1, 0.0, 0.05]) * t), [0.01 * t, 0.0, 0.4])


def frame_arrays(i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rgb = np.full((H, W, 3), 10 * i, np.uint8)
    depth = np.full((H, W), 0.4 + 0.01 * i)
    mask = np.zeros((H, W), bool)
    mask[3:9, 4:12] = True
    return rgb, depth, mask


def make_sequence(root: Path, n: int = 4, masks: str = "first") -> Path:
    """A valid DESIGN-layout sequence of n synthetic frames; masks 'first', 'all' or 'none'."""
    w = SequenceWriter(root, K)
    for i in range(n):
        rgb, depth, mask = frame_arrays(i)
        keep = masks == "all" or (masks == "first" and i == 0)
        w.write_frame(i, rgb, depth, mask if keep else None, pose(i))
    return root


def raises(match_path: Path, problem: str):
    """Expect a SequenceError whose one-line message names the file and the problem."""
    return pytest.raises(SequenceError, match=rf"^{re.escape(str(match_path))}: .*{problem}")


# ------------------------------------------------------------------------------------------------ valid input


def test_sequence_round_trip(tmp_path: Path):
    seq = open_sequence(make_sequence(tmp_path / "s", masks="all"))
    assert isinstance(seq, FolderSequence) and len(seq) == 4 and seq.ids == ["000000", "000001", "000002", "000003"]
    np.testing.assert_allclose(seq.K, K)
    f = seq[2]
    rgb, depth, mask = frame_arrays(2)
    np.testing.assert_array_equal(f.rgb, rgb)
    np.testing.assert_allclose(f.depth, depth, atol=5e-4)  # millimetre PNG
    assert f.depth.dtype == np.float32
    np.testing.assert_array_equal(f.mask, mask)
    gt = seq.gt_poses()
    assert list(gt) == seq.ids
    np.testing.assert_allclose(gt["000003"], pose(3), atol=1e-8)
    assert seq.gt_model() is None and seq.gt_visible_points() is None


def test_the_digest_names_the_frames_not_the_folder(tmp_path: Path):
    """Two folders with the same files have the same digest wherever they lie; one changed depth value, or a
    frame renamed, gives another."""
    a = make_sequence(tmp_path / "a", masks="all")
    b = make_sequence(tmp_path / "elsewhere" / "b", masks="all")
    assert sequence_digest(a) == sequence_digest(b)
    depth = a / "depth" / "000002.png"
    d = cv2.imread(str(depth), cv2.IMREAD_UNCHANGED)
    d[0, 0] += 1
    cv2.imwrite(str(depth), d)
    assert sequence_digest(a) != sequence_digest(b)
    mask = b / "masks" / "000003.png"
    mask.rename(b / "masks" / "000004.png")
    assert sequence_digest(b) != sequence_digest(make_sequence(tmp_path / "c", masks="all"))


def test_optional_masks_and_gt_model(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    box = trimesh.creation.box((0.1, 0.02, 0.02))
    SequenceWriter(root, K).write_model(box, box.vertices[:5])
    seq = open_sequence(root)
    assert seq[0].mask is not None and seq[1].mask is None
    np.testing.assert_allclose(seq.gt_model().vertices, box.vertices)
    assert seq.gt_visible_points().shape == (5, 3)


def test_depth_scale_option(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    for i in range(4):  # re-save the depth in 0.1 mm units
        cv2.imwrite(str(root / "depth" / f"{i:06d}.png"), np.full((H, W), 4000 + 100 * i, np.uint16))
    assert open_sequence(root, depth_scale=1e-4)[1].depth[0, 0] == pytest.approx(0.41)
    assert open_sequence(root)[1].depth[0, 0] == pytest.approx(4.1)  # millimetres by default


def test_reading_is_lazy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    root = make_sequence(tmp_path / "s", n=5)
    (root / "rgb" / "000003.png").write_bytes(b"broken")  # opening must not touch frame 3
    read: list[str] = []
    original = sio.read_rgb

    def spy(path: Path) -> np.ndarray:
        read.append(path.name)
        return original(path)

    monkeypatch.setattr(sio, "read_rgb", spy)
    seq = open_sequence(root)
    assert read == ["000000.png"]  # the first frame is validated up front, nothing else
    seq[4]
    assert read == ["000000.png", "000004.png"]
    with raises(root / "rgb" / "000003.png", "unreadable image"):
        seq[3]


def test_frames_read_ahead_come_in_order_and_a_bad_one_raises_at_its_turn(tmp_path: Path):
    """`Sequence.read_ahead` (the tracking loop's reader) gives the frames seq[i] gives, in order, each with what
    ``prepare`` made of it; an unreadable frame raises its one-line error only once the frames before it have been
    handed over."""
    root = make_sequence(tmp_path / "s", n=6)
    seq = open_sequence(root)
    items = list(seq.read_ahead(1, prepare=lambda f: f.id))
    assert [f.id for f, _ in items] == [made for _, made in items] == seq.ids[1:]
    for i, (f, _) in enumerate(items, start=1):
        assert np.array_equal(f.rgb, seq[i].rgb) and np.array_equal(f.depth, seq[i].depth)
    assert {made for _, made in seq.read_ahead(0)} == {None}
    (root / "rgb" / "000004.png").write_bytes(b"broken")
    got = []
    with raises(root / "rgb" / "000004.png", "unreadable image"):
        for f, _ in seq.read_ahead(0):
            got.append(f.id)
    assert got == seq.ids[:4]
    assert [f.id for _, (f, _) in zip(range(2), seq.read_ahead(0), strict=False)] == seq.ids[:2]  # stopping early


# ------------------------------------------------------------------------------------------------ bad input


def test_missing_sequence_folder(tmp_path: Path):
    with raises(tmp_path / "nope", "sequence folder does not exist"):
        open_sequence(tmp_path / "nope")


def test_missing_cam_k(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    (root / "cam_K.txt").unlink()
    with raises(root / "cam_K.txt", "missing file"):
        open_sequence(root)


@pytest.mark.parametrize(
    ("text", "problem"),
    [("1 0 0\n0 1 0\n", "expected a 3x3 matrix, got 2x3"), ("1 0 0 0\n0 1 0 0\n0 0 1 0\n", "got 3x4"),
     ("a b c\n1 2 3\n4 5 6\n", "not a numeric matrix"), ("1 0 0\n0 nan 0\n0 0 1\n", "NaN"),
     ("0 0 8\n0 0 6\n0 0 1\n", r"not a camera matrix .*\(fx 0, fy 0"),  # no focal length
     ("20 0 0\n0 20 0\n8 6 1\n", r"not a camera matrix .*last row 8 6 1")],  # transposed
)
def test_cam_k_not_3x3(tmp_path: Path, text: str, problem: str):
    root = make_sequence(tmp_path / "s")
    (root / "cam_K.txt").write_text(text)
    with raises(root / "cam_K.txt", problem):
        open_sequence(root)


def test_frame_numbering_gap(tmp_path: Path):
    root = make_sequence(tmp_path / "s", n=5)
    (root / "rgb" / "000002.png").unlink()
    with raises(root / "rgb", "frame numbering gap: 000001 is followed by 000003"):
        open_sequence(root)


def test_no_frames(tmp_path: Path):
    root = tmp_path / "s"
    SequenceWriter(root, K)
    with raises(root / "rgb", "no frames"):
        open_sequence(root)


def test_missing_depth_frame(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    (root / "depth" / "000002.png").unlink()
    with raises(root / "depth" / "000002.png", "missing depth frame"):
        open_sequence(root)


def test_rgb_depth_size_mismatch(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    cv2.imwrite(str(root / "rgb" / "000001.png"), np.zeros((H, W + 4, 3), np.uint8))
    seq = open_sequence(root)
    with raises(root / "rgb" / "000001.png", f"size {W + 4}x{H} != depth size {W}x{H}"):
        seq[1]


def test_mask_depth_size_mismatch(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    cv2.imwrite(str(root / "masks" / "000000.png"), np.full((H + 2, W, 1), 255, np.uint8))
    with raises(root / "masks" / "000000.png", f"size {W}x{H + 2} != depth size {W}x{H}"):
        open_sequence(root)


def test_depth_not_uint16(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    cv2.imwrite(str(root / "depth" / "000000.png"), np.full((H, W), 200, np.uint8))
    with raises(root / "depth" / "000000.png", "depth must be uint16 \\(got uint8\\)"):
        open_sequence(root)


def test_depth_with_colour_channels(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    cv2.imwrite(str(root / "depth" / "000000.png"), np.full((H, W, 3), 400, np.uint16))
    with raises(root / "depth" / "000000.png", "single-channel"):
        open_sequence(root)


def test_depth_in_metres_by_mistake(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    cv2.imwrite(str(root / "depth" / "000000.png"), np.ones((H, W), np.uint16))  # 0.4 m rounded to 1 unit
    with raises(root / "depth" / "000000.png", "median depth is 1.00 units of 0.001 m: depth looks saved in metres"):
        open_sequence(root)
    with raises(root / "depth" / "000000.png", "units of 0.0001 m"):
        open_sequence(root, depth_scale=1e-4)


@pytest.mark.parametrize("kind", ["rgb", "depth", "masks"])
def test_unreadable_png(tmp_path: Path, kind: str):
    root = make_sequence(tmp_path / "s", masks="all")
    bad = root / kind / "000001.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    seq = open_sequence(root)
    with raises(bad, "unreadable image"):
        seq[1]


def test_empty_first_mask(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    cv2.imwrite(str(root / "masks" / "000000.png"), np.zeros((H, W), np.uint8))
    with raises(root / "masks" / "000000.png", "first-frame mask is empty"):
        open_sequence(root)


def test_inverted_first_mask(tmp_path: Path):
    """A mask saved inverted (the view around the instrument) is refused; one over most of the image that leaves the
    corners to the background is an instrument seen close up and is taken."""
    root = make_sequence(tmp_path / "s")
    path = root / "masks" / "000000.png"
    cv2.imwrite(str(path), np.where(frame_arrays(0)[2], 0, 255).astype(np.uint8))
    with raises(path, "covers 75% of the image and its corners: inverted"):
        open_sequence(root)
    close = np.zeros((H, W), np.uint8)
    close[1:-1, 1:-1] = 255  # 73 % of the image
    cv2.imwrite(str(path), close)
    assert open_sequence(root)[0].mask.mean() > 0.7


def test_missing_first_mask(tmp_path: Path):
    root = make_sequence(tmp_path / "s", masks="none")
    with raises(root / "masks" / "000000.png", "missing first-frame mask"):
        open_sequence(root)


def test_bad_gt_pose(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    (root / "gt" / "ob_in_cam" / "000001.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
    seq = open_sequence(root)
    with raises(root / "gt" / "ob_in_cam" / "000001.txt", "expected a 4x4 matrix, got 3x3"):
        seq.gt_poses()


def test_error_message_is_one_line(tmp_path: Path):
    root = make_sequence(tmp_path / "s")
    (root / "cam_K.txt").write_text("x y\n")
    with pytest.raises(SequenceError) as e:
        open_sequence(root)
    assert "\n" not in str(e.value) and e.value.path == root / "cam_K.txt"


# ------------------------------------------------------------------------------------------------ results


def test_result_writer_keeps_poses_written_before_a_crash(tmp_path: Path):
    out = tmp_path / "out"
    script = (
        "import os, sys, numpy as np\n"
        "from surgtrack.io import ResultWriter\n"
        "w = ResultWriter(sys.argv[1])\n"
        "for i in range(3):\n"
        "    w.write(f'{i:06d}', np.eye(4) * (i + 1) if i != 1 else None, {'status': 'tracked'})\n"
        "os._exit(9)  # killed mid-run: no close, no flush at exit\n"
    )
    run = subprocess.run([sys.executable, "-c", script, str(out)], capture_output=True, text=True)
    assert run.returncode == 9, run.stderr
    poses = read_poses(out / "ob_in_cam")
    assert list(poses) == ["000000", "000002"]  # frame 1 was lost: logged, no pose file
    np.testing.assert_allclose(poses["000002"], np.eye(4) * 3)
    lines = [json.loads(x) for x in (out / "track.jsonl").read_text().splitlines()]
    assert [x["frame"] for x in lines] == ["000000", "000001", "000002"]


def test_result_writer_survives_an_exception(tmp_path: Path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError), ResultWriter(out) as w:
        for i in range(5):
            if i == 3:
                raise RuntimeError("tracker crashed")
            w.write(f"{i:06d}", pose(i), {"status": "tracked"})
    assert sorted(read_poses(out / "ob_in_cam")) == ["000000", "000001", "000002"]
    np.testing.assert_allclose(read_poses(out / "ob_in_cam")["000002"], pose(2), atol=1e-8)
    assert len((out / "track.jsonl").read_text().splitlines()) == 3


def test_results_into_a_file_or_below_one_is_a_one_line_error(tmp_path: Path):
    taken = tmp_path / "poses.txt"
    taken.write_text("kept")
    with raises(taken, "is a file, not a folder"):
        ResultWriter(taken)
    with raises(taken / "out", "cannot make the folder"):
        ResultWriter(taken / "out")
    assert taken.read_text() == "kept"


def test_the_track_log_reads_back_as_written_and_a_broken_one_names_its_line(tmp_path: Path):
    out = tmp_path / "out"
    with ResultWriter(out) as w:
        w.write("000000", pose(0), {"status": "tracked", "ms": {"graph": 12.5}})
        w.write("000001", None, {"status": "lost", "reason": "hidden"})
    rows = read_track_log(out)
    assert rows == [{"frame": "000000", "status": "tracked", "ms": {"graph": 12.5}},
                    {"frame": "000001", "status": "lost", "reason": "hidden"}]
    with open(out / "track.jsonl", "a") as log:
        log.write('{"frame": "000002", "sta')  # a run killed mid-line
    with pytest.raises(SequenceError, match=r"track\.jsonl.*line 3 is not JSON"):
        read_track_log(out)
    with pytest.raises(SequenceError, match="missing file"):
        read_track_log(tmp_path / "nowhere")


def test_pose_writes_are_atomic(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    path = tmp_path / "ob_in_cam" / "000000.txt"
    write_pose(path, pose(1))

    def crash(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(sio.os, "replace", crash)
    with pytest.raises(OSError):
        write_pose(path, pose(2))
    monkeypatch.undo()
    np.testing.assert_allclose(read_poses(path.parent)["000000"], pose(1), atol=1e-8)  # old pose intact
    assert list(read_poses(path.parent)) == ["000000"]  # the half-done temporary is never read as a pose


def test_result_writer_records_the_runs_config_first(tmp_path: Path):
    cfg = TrackerConfig()
    cfg.pool.K = 4
    out = tmp_path / "out"
    with ResultWriter(out, cfg.to_dict()):
        assert TrackerConfig.from_dict(json.loads((out / "config.json").read_text())).pool.K == 4  # before any frame
    with ResultWriter(out):  # a writer given no config leaves the one there
        pass
    assert json.loads((out / "config.json").read_text())["pool"]["K"] == 4


def test_result_writer_mesh(tmp_path: Path):
    box = trimesh.creation.box((0.1, 0.02, 0.02))
    with ResultWriter(tmp_path / "out") as w:
        w.write_mesh(box)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["mesh.ply", "ob_in_cam", "track.jsonl"]
    np.testing.assert_allclose(sio.load_mesh(tmp_path / "out" / "mesh.ply").vertices, box.vertices, atol=1e-6)


# ------------------------------------------------------------------------------------------------ BOP


def make_bop(root: Path) -> Path:
    """A two-frame BOP scene with objects 3 and 5, depth in 0.1 mm units, model of object 5 in millimetres."""
    scene = root / "test" / "000002"
    for sub in ("rgb", "depth", "mask_visib"):
        (scene / sub).mkdir(parents=True)
    cams, gts = {}, {}
    for n in (0, 1):
        rgb, depth, mask = frame_arrays(n)
        cv2.imwrite(str(scene / "rgb" / f"{n:06d}.png"), rgb)
        cv2.imwrite(str(scene / "depth" / f"{n:06d}.png"), np.round(depth * 1e4).astype(np.uint16))
        cv2.imwrite(str(scene / "mask_visib" / f"{n:06d}_000000.png"), np.zeros((H, W), np.uint8))
        cv2.imwrite(str(scene / "mask_visib" / f"{n:06d}_000001.png"), mask.astype(np.uint8) * 255)
        cams[str(n)] = {"cam_K": K.ravel().tolist(), "depth_scale": 0.1}
        T = pose(n)
        gts[str(n)] = [
            {"obj_id": 3, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0, 0, 900]},
            {"obj_id": 5, "cam_R_m2c": T[:3, :3].ravel().tolist(), "cam_t_m2c": (T[:3, 3] * 1000).tolist()},
        ]
    (scene / "scene_camera.json").write_text(json.dumps(cams))
    (scene / "scene_gt.json").write_text(json.dumps(gts))
    (root / "models").mkdir()
    trimesh.creation.box((100.0, 20.0, 20.0)).export(root / "models" / "obj_000005.ply")
    return scene


def test_bop_scene(tmp_path: Path):
    scene = make_bop(tmp_path / "bop")
    seq = open_sequence(scene, obj_id=5)
    assert isinstance(seq, BopScene) and seq.ids == ["000000", "000001"]
    f = seq[1]
    rgb, depth, mask = frame_arrays(1)
    np.testing.assert_array_equal(f.rgb, rgb[..., ::-1])  # written with cv2 (BGR), read back as RGB
    np.testing.assert_allclose(f.depth, depth, atol=1e-4)  # depth_scale 0.1 mm
    np.testing.assert_array_equal(f.mask, mask)  # slot 1 of scene_gt is object 5
    np.testing.assert_allclose(seq.gt_poses()["000001"], pose(1), atol=1e-8)  # millimetres to metres
    np.testing.assert_allclose(seq.gt_model().extents, [0.1, 0.02, 0.02])  # model rescaled to metres
    # Without --obj-id the first listed object is taken; object 3 has an empty first mask.
    with raises(scene / "mask_visib" / "000000_000000.png", "first-frame mask is empty"):
        open_sequence(scene)


def test_bop_scene_errors(tmp_path: Path):
    scene = make_bop(tmp_path / "bop")
    (scene / "scene_gt.json").write_text("{ not json")
    with raises(scene / "scene_gt.json", "invalid JSON"):
        open_sequence(scene, obj_id=5)
    (scene / "scene_gt.json").unlink()
    with raises(scene / "mask_visib" / "000000_000000.png", "missing first-frame mask"):
        open_sequence(scene, obj_id=5)
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [1, 2, 3]}}))
    with raises(scene / "scene_camera.json", "frame 0: cam_K missing or not 3x3"):
        open_sequence(scene, obj_id=5)
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [20, 0, 8, 0, -20, 6, 0, 0, 1]}}))
    with raises(scene / "scene_camera.json", r"frame 0: cam_K not a camera matrix .*fy -20"):
        open_sequence(scene, obj_id=5)


def test_result_writer_replaces_an_earlier_runs_poses_and_mesh(tmp_path):
    from surgtrack.io import ResultWriter, write_pose

    write_pose(tmp_path / "ob_in_cam" / "000099.txt", np.eye(4))
    (tmp_path / "mesh.ply").write_text("old")
    with ResultWriter(tmp_path) as writer:
        writer.write("000000", np.eye(4), {"status": "tracked"})
    assert sorted(p.name for p in (tmp_path / "ob_in_cam").iterdir()) == ["000000.txt"]
    assert not (tmp_path / "mesh.ply").exists()
