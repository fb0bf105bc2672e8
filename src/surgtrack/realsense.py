"""Intel RealSense input: a live camera or a recorded RealSense file, read through one code path.

    with RealSenseSource() as source:                 # live camera (colour + depth)
        for frame in source: ...
    with RealSenseSource(file="scan.db3") as source:  # a recording, every frame in order, as fast as it is read
        for frame in source: ...

Depth is aligned to the colour image with ``rs.align`` (skipped when the depth stream already is the colour
camera's: identical intrinsics and identity extrinsics), converted to metres with the device's depth scale, and the
intrinsics are the colour stream's. :func:`record_sequence` writes a sequence folder as a RealSense recording
(pyrealsense2 2.59 records ROS 2 ``.db3`` files only), so that recorded data plays back like a camera.
"""

from __future__ import annotations

import queue
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from .io import DEPTH_SCALE_MM, Frame, SequenceError, open_sequence

_COLOUR_FORMATS = {"rgb8": False, "bgr8": True, "rgba8": False, "bgra8": True}  # format -> channels in BGR order


class RealSenseError(RuntimeError):
    """No camera, an unreadable recording or a stream the reader cannot use; the message is one line."""


def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError as e:  # pragma: no cover - pyrealsense2 is a dependency of the live workflow
        raise RealSenseError(f"pyrealsense2 is not installed ({e}); pip install pyrealsense2") from None
    return rs


def intrinsics_matrix(intr) -> np.ndarray:
    """3x3 K from an ``rs.intrinsics``."""
    return np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])


def _already_aligned(depth_profile, colour_profile) -> bool:
    """True when the depth stream is registered to the colour camera already (alignment would be the identity)."""
    di = depth_profile.as_video_stream_profile().get_intrinsics()
    ci = colour_profile.as_video_stream_profile().get_intrinsics()
    same_intr = (di.width, di.height) == (ci.width, ci.height) and np.allclose(
        [di.fx, di.fy, di.ppx, di.ppy], [ci.fx, ci.fy, ci.ppx, ci.ppy]) and not np.any(di.coeffs)
    if not same_intr:
        return False
    try:
        ext = depth_profile.get_extrinsics_to(colour_profile)
    except RuntimeError:
        return False
    return np.allclose(ext.rotation, np.eye(3).ravel()) and np.allclose(ext.translation, 0.0)


class _Recording:
    """Every colour and depth frame of a recording, in order, as (colour, depth) pairs.

    The recording's sensors are read directly into one short queue, which playback (not in real time) waits on when
    it is full, and the two streams are paired here by timestamp, within half a frame period. A pipeline's syncer
    is not used: it passes one stream's first frames on alone, or drops them, when the other stream's first frame
    reaches it later, which on a loaded machine lost a recording's first frames.
    """

    def __init__(self, rs, path: Path, timeout_ms: int):
        self.path, self.timeout_ms = path, timeout_ms
        try:
            self.device = rs.context().load_device(str(path))
        except RuntimeError as e:
            raise RealSenseError(f"{path}: cannot open the recording ({e})") from None
        self._playback = self.device.as_playback()
        self._playback.set_real_time(False)
        self.profiles: dict[str, object] = {}
        self._sensors: list[tuple[object, list]] = []
        kinds = {rs.stream.color: "colour", rs.stream.depth: "depth"}
        for sensor in self.device.query_sensors():
            chosen = []
            for profile in sensor.get_stream_profiles():
                kind = kinds.get(profile.stream_type())
                if kind is not None and kind not in self.profiles:
                    self.profiles[kind] = profile
                    chosen.append(profile)
            if chosen:
                self._sensors.append((sensor, chosen))
        missing = [k for k in kinds.values() if k not in self.profiles]
        if missing:
            raise RealSenseError(f"{path}: needs a colour and a depth stream (no {' or '.join(missing)} stream)")
        self._stopped = rs.playback_status.stopped
        self._queue: queue.Queue = queue.Queue(maxsize=8)
        self._kind = {p.unique_id(): kind for kind, p in self.profiles.items()}
        self._running = True
        try:
            # Paused until every sensor streams: playback starts with the first sensor started, and the frames it
            # reads for a sensor not started yet are lost.
            self._playback.pause()
            for sensor, profiles in self._sensors:
                sensor.open(profiles)
                sensor.start(self._on_frame)
            self._playback.resume()
        except RuntimeError as e:
            self.close()
            raise RealSenseError(f"{path}: cannot start playback ({e})") from None
        fps = min(float(p.fps()) for p in self.profiles.values())
        self.tol_ms = 500.0 / fps if fps > 0 else 1.0

    def _on_frame(self, frame) -> None:
        kind = self._kind[frame.get_profile().unique_id()]
        while self._running:  # waiting here holds the playback back until the reader has caught up
            try:
                self._queue.put((kind, frame), timeout=0.1)
                return
            except queue.Full:
                continue

    def _next(self) -> tuple | None:
        """The next (kind, frame) of either stream, or None once the recording has ended."""
        waited = idle = 0
        while waited < self.timeout_ms:
            try:
                return self._queue.get(timeout=0.1)
            except queue.Empty:
                pass
            waited += 100
            if self._playback.current_status() == self._stopped:
                # The reader is done, but frames it read can still be on their way to the queue: the recording has
                # ended once none has come for a while.
                idle += 100
                if idle >= min(1000, self.timeout_ms // 2):
                    return None
        raise RealSenseError(f"{self.path}: playback stalled for {self.timeout_ms / 1000:.0f} s")

    def pairs(self) -> Iterator[tuple]:
        """(colour, depth) frames whose timestamps are within ``tol_ms``, in order; a frame the other stream has
        none for is skipped (each stream comes in order, so a frame older than the other stream's oldest waiting
        one by more than ``tol_ms`` has none)."""
        waiting: dict[str, deque] = {"colour": deque(maxlen=64), "depth": deque(maxlen=64)}
        while self._running:
            while waiting["colour"] and waiting["depth"]:
                colour, depth = waiting["colour"][0], waiting["depth"][0]
                dt = colour.get_timestamp() - depth.get_timestamp()
                if abs(dt) <= self.tol_ms:
                    waiting["colour"].popleft()
                    waiting["depth"].popleft()
                    yield colour, depth
                else:
                    waiting["depth" if dt > 0 else "colour"].popleft()
            item = self._next()
            if item is None:
                return
            waiting[item[0]].append(item[1])

    def close(self) -> None:
        """Stop the playback (safe to call twice)."""
        self._running = False
        while not self._queue.empty():
            self._queue.get_nowait()
        for sensor, _ in self._sensors:
            for step in (sensor.stop, sensor.close):
                try:
                    step()
                except RuntimeError:  # not started or not opened
                    pass


class _Joiner:
    """One frameset of a colour and a depth frame that came apart (what ``rs.align`` and the camera path take),
    made by a processing block."""

    def __init__(self, rs):
        self._depth = None
        self._queue = rs.frame_queue(1, keep_frames=True)
        self._block = rs.processing_block(self._join)
        self._block.start(self._queue)

    def _join(self, colour, source) -> None:
        source.frame_ready(source.allocate_composite_frame([self._depth, colour]))

    def __call__(self, colour, depth):
        self._depth = depth
        self._block.invoke(colour)
        self._depth = None
        return self._queue.wait_for_frame(1000).as_frameset()


class RealSenseSource:
    """Frames (``surgtrack.io.Frame``, depth in metres aligned to colour) from a live camera or a recorded file.

    ``file`` None opens the first connected camera with colour and depth at ``width`` x ``height`` and ``fps``;
    otherwise the recording is played once, not in real time, so every recorded frame is read in order.
    ``align`` None aligns depth to colour unless the depth stream is registered to the colour camera already.
    """

    def __init__(self, file: Path | str | None = None, width: int = 640, height: int = 480, fps: int = 30,
                 timeout_s: float = 5.0, align: bool | None = None):
        rs = _rs()
        self.file = None if file is None else Path(file)
        self.timeout_ms = int(timeout_s * 1000)
        self._pipeline = self._recording = None
        if self.file is not None:
            if not self.file.is_file():
                raise RealSenseError(f"{self.file}: no such recording")
            self._recording = _Recording(rs, self.file, self.timeout_ms)
            self._join = _Joiner(rs)
            device = self._recording.device
            colour, depth = self._recording.profiles["colour"], self._recording.profiles["depth"]
        else:
            if len(rs.context().query_devices()) == 0:
                raise RealSenseError("no RealSense camera connected (give a recording with --file)")
            config = rs.config()
            config.enable_stream(rs.stream.depth, width, height, rs.format.z16, fps)
            config.enable_stream(rs.stream.color, width, height, rs.format.rgb8, fps)
            self._pipeline = rs.pipeline()
            try:
                profile = self._pipeline.start(config)
            except RuntimeError as e:
                raise RealSenseError(f"RealSense camera: cannot start streaming ({e})") from None
            device = profile.get_device()
            colour, depth = profile.get_stream(rs.stream.color), profile.get_stream(rs.stream.depth)
        self._running = True
        where = self.file or "camera"
        try:
            self.depth_scale = float(device.first_depth_sensor().get_depth_scale())
        except RuntimeError as e:
            self.close()
            raise RealSenseError(f"{where}: has no depth sensor ({e})") from None
        fmt = str(colour.format()).split(".")[-1]
        if fmt not in _COLOUR_FORMATS:
            self.close()
            raise RealSenseError(f"{where}: colour format {fmt} is not supported (use one of "
                                 f"{', '.join(_COLOUR_FORMATS)})")
        self._bgr = _COLOUR_FORMATS[fmt]
        intr = colour.as_video_stream_profile().get_intrinsics()
        self.K = intrinsics_matrix(intr)
        self.size = (intr.width, intr.height)
        self.fps = float(colour.fps())
        if align is None:
            align = not _already_aligned(depth, colour)
        self._align = rs.align(rs.stream.color) if align else None

    def _framesets(self) -> Iterator:
        """Framesets of the camera, or of the recording's (colour, depth) pairs joined (`_Joiner`)."""
        if self._recording is not None:
            for colour, depth in self._recording.pairs():
                yield self._join(colour, depth)
            return
        while self._running:
            ok, frames = self._pipeline.try_wait_for_frames(self.timeout_ms)
            if not ok:
                raise RealSenseError(f"camera sent no frames for {self.timeout_ms / 1000:.0f} s")
            yield frames

    def __iter__(self) -> Iterator[Frame]:
        index = 0
        for frames in self._framesets():
            if self._align is not None:
                frames = self._align.process(frames)
            colour, depth = frames.get_color_frame(), frames.get_depth_frame()
            if not colour or not depth:
                continue
            rgb = np.asanyarray(colour.get_data())[..., :3]
            rgb = np.array(rgb[..., ::-1] if self._bgr else rgb, order="C")  # a copy: librealsense reuses buffers
            z = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(self.depth_scale)
            yield Frame(index, f"{index:06d}", rgb, z, self.K.copy())
            index += 1

    def close(self) -> None:
        """Stop streaming (safe to call twice)."""
        self._running = False
        if self._recording is not None:
            self._recording.close()
            self._recording = None
        if self._pipeline is not None:
            self._pipeline.stop()
            self._pipeline = None

    def __enter__(self) -> RealSenseSource:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _video_stream(rs, kind, uid: int, fmt, bpp: int, intr, fps: int):
    vs = rs.video_stream()
    vs.type, vs.index, vs.uid = kind, 0, uid
    vs.width, vs.height, vs.fps, vs.bpp, vs.fmt, vs.intrinsics = intr.width, intr.height, fps, bpp, fmt, intr
    return vs


def _inject(rs, sensor, profile, pixels: np.ndarray, bpp: int, index: int, fps: float,
            depth_units: float | None = None) -> None:
    frame = rs.software_video_frame()
    frame.pixels = np.ascontiguousarray(pixels)
    frame.stride = pixels.shape[1] * bpp
    frame.bpp = bpp
    frame.timestamp = index * 1000.0 / fps
    frame.domain = rs.timestamp_domain.hardware_clock
    frame.frame_number = index
    frame.profile = profile
    if depth_units is not None:
        frame.depth_units = depth_units
    sensor.on_video_frame(frame)


def record_sequence(seq_folder: Path | str, path: Path | str, fps: int = 30, depth_scale: float = DEPTH_SCALE_MM,
                    max_frames: int | None = None) -> int:
    """Write a sequence folder (DESIGN layout) as a RealSense recording at ``path`` (``.db3``); returns the frame
    count. Colour is rgb8, depth z16 in millimetres (depth units 0.001) registered to the colour camera, both with
    the folder's intrinsics. The recording plays back with :class:`RealSenseSource` and the RealSense tools."""
    rs = _rs()
    path = Path(path)
    if path.suffix != ".db3":
        raise RealSenseError(f"{path}: RealSense recordings are written as .db3 files")
    seq = open_sequence(seq_folder, depth_scale=depth_scale)
    first = seq[0]
    h, w = first.depth.shape
    intr = rs.intrinsics()
    intr.width, intr.height = w, h
    intr.fx, intr.fy, intr.ppx, intr.ppy = (float(v) for v in (seq.K[0, 0], seq.K[1, 1], seq.K[0, 2], seq.K[1, 2]))
    intr.model, intr.coeffs = rs.distortion.none, [0.0] * 5
    device = rs.software_device()
    device.register_info(rs.camera_info.name, "surgtrack recording")
    device.register_info(rs.camera_info.serial_number, "0")
    depth_sensor, colour_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    depth_sensor.add_read_only_option(rs.option.depth_units, DEPTH_SCALE_MM)
    depth_profile = depth_sensor.add_video_stream(_video_stream(rs, rs.stream.depth, 0, rs.format.z16, 2, intr, fps),
                                                  True)
    colour_profile = colour_sensor.add_video_stream(
        _video_stream(rs, rs.stream.color, 1, rs.format.rgb8, 3, intr, fps), True)
    identity = rs.extrinsics()
    identity.rotation, identity.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0, 0.0, 0.0]
    depth_profile.register_extrinsics_to(colour_profile, identity)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    recorder = rs.recorder(str(path), device)
    received = {"depth": 0, "colour": 0}

    def counter(key: str):
        return lambda _frame: received.__setitem__(key, received[key] + 1)

    depth_sensor.open(depth_profile)
    colour_sensor.open(colour_profile)
    depth_sensor.start(counter("depth"))
    colour_sensor.start(counter("colour"))
    n = len(seq) if max_frames is None else min(len(seq), max_frames)
    try:
        for i in range(n):
            frame = first if i == 0 else seq[i]
            if frame.depth.shape != (h, w):
                raise SequenceError(seq.root, f"frame {frame.id}: size differs from the first frame's")
            mm = np.clip(np.round(np.nan_to_num(frame.depth) / DEPTH_SCALE_MM), 0, 65535).astype(np.uint16)
            _inject(rs, depth_sensor, depth_profile.as_video_stream_profile(), mm, 2, i, fps, DEPTH_SCALE_MM)
            _inject(rs, colour_sensor, colour_profile.as_video_stream_profile(), frame.rgb, 3, i, fps)
    finally:
        for sensor in (depth_sensor, colour_sensor):
            sensor.stop()
            sensor.close()
        del recorder  # the recording is finalised when the recorder is destroyed
    if received["depth"] != n or received["colour"] != n:
        raise RealSenseError(f"{path}: recorded {received['depth']} depth and {received['colour']} colour frames "
                             f"of {n}")
    return n


def box_mask(depth: np.ndarray, box: tuple[int, int, int, int], slab_m: float = 0.02, min_seed: float = 0.01,
             jump_m: float = 0.01, min_component: float = 0.1, close_px: int = 5) -> np.ndarray:
    """First-frame instrument mask from a box drawn around it: the depth-consistent pixels inside the box.

    Rule, inside the box (x0, y0, x1, y1; x1 and y1 exclusive), over pixels with valid depth:

    1. Seed, the nearest dominant depth cluster: the nearest depth slab ``slab_m`` thick that holds at least
       ``min_seed`` of the box's valid pixels (and 20 pixels; failing that, the densest slab), so flying pixels and
       specks in front do not count.
    2. Grow: the mask is every pixel joined to a seed pixel by a path of 8-neighbours whose depths differ by at
       most ``jump_m`` (a depth-continuous surface, so a shaft tilted away from the camera is followed to its far
       end, while the jump at its silhouette stops the growth into the tissue behind); connected regions smaller
       than ``min_component`` times the largest are dropped.
    3. Fill: a morphological closing (``close_px`` square) adds the enclosed pixels that have no depth (specular
       dropouts on the metal) or a depth within the region's depth range +- ``jump_m``.

    It fits an instrument held clear of what lies behind it; a hand touching it at the same depth joins the mask,
    so draw the box around a part of the instrument that no hand touches.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    h, w = depth.shape
    x0, y0, x1, y1 = (int(v) for v in box)
    x0, x1 = max(0, min(x0, x1)), min(w, max(x0, x1))
    y0, y1 = max(0, min(y0, y1)), min(h, max(y0, y1))
    if x1 - x0 < 2 or y1 - y0 < 2:
        raise ValueError(f"box {tuple(box)} is empty inside the {w}x{h} image")
    z = depth[y0:y1, x0:x1].astype(np.float64)
    valid = (z > 0) & np.isfinite(z)
    values = np.sort(z[valid])
    need = max(20, int(np.ceil(min_seed * values.size)))
    if values.size < need:
        raise ValueError(f"box {tuple(box)} holds only {values.size} pixels with valid depth")
    in_slab = np.searchsorted(values, values + slab_m, side="right") - np.arange(values.size)
    dense = in_slab >= need
    near = values[int(np.argmax(dense)) if dense.any() else int(np.argmax(in_slab))]  # else the densest slab
    seed = valid & (z >= near) & (z <= near + slab_m)

    # Components of the graph whose edges join 8-neighbours with continuous depth.
    bh, bw = z.shape
    ids = np.arange(bh * bw).reshape(bh, bw)
    rows, cols = [], []
    for sa, sb in [((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                   ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
                   ((slice(None, -1), slice(None, -1)), (slice(1, None), slice(1, None))),
                   ((slice(None, -1), slice(1, None)), (slice(1, None), slice(None, -1)))]:
        joined = valid[sa] & valid[sb] & (np.abs(z[sa] - z[sb]) <= jump_m)
        rows.append(ids[sa][joined])
        cols.append(ids[sb][joined])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(r.size, dtype=np.int8), (r, c)), shape=(bh * bw, bh * bw))
    _, labels = connected_components(graph, directed=False)
    labels = labels.reshape(bh, bw)
    chosen = np.unique(labels[seed])
    sizes = np.array([np.count_nonzero(labels == k) for k in chosen])
    chosen = chosen[sizes >= min_component * sizes.max()]
    inside = np.isin(labels, chosen) & valid
    if close_px > 1:
        closed = cv2.morphologyEx(inside.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((close_px, close_px), np.uint8))
        zs = z[inside]
        inside |= closed.astype(bool) & (~valid | ((z >= zs.min() - jump_m) & (z <= zs.max() + jump_m)))
    mask = np.zeros((h, w), dtype=bool)
    mask[y0:y1, x0:x1] = inside
    return mask


def parse_box(text: str) -> tuple[int, int, int, int]:
    """'x0,y0,x1,y1' (pixels) -> a tuple of ints; ValueError names what is wrong."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = tuple(int(round(float(p))) for p in parts)
    except ValueError:
        raise ValueError(f"box must be x0,y0,x1,y1 in pixels, got {text!r}") from None
    if len(values) != 4:
        raise ValueError(f"box must be x0,y0,x1,y1 in pixels, got {text!r}")
    return values  # type: ignore[return-value]
