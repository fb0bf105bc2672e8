"""How long `surgtrack live --file` waits for each frame of a RealSense recording, with and without work between.

    .venv/bin/python benchmarks/playback_wait.py SEQUENCE

SEQUENCE (a sequence folder, e.g. ``runs/full/data/endoscope_1``) is recorded to a ROS2 .db3 file through
pyrealsense2 (`realsense.record_sequence`, as the tests record theirs) and played back through
`realsense.RealSenseSource`, the reader `surgtrack live` uses: once taking each frame as soon as it comes, once
tracking each frame in between (`SurgTracker` with the default configuration and the SDF off, first mask from the
sequence, as `surgtrack live --mask` tracks). Printed: frames played, the mean time the caller waited for a frame
and the mean time tracking took. librealsense plays a recording in threads of its own; when the wait while
tracking is small against the tracking, frames are decoded while the tracker works, and a read-ahead thread of
ours would gain nothing.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from surgtrack.config import SDFConfig, TrackerConfig
from surgtrack.io import Frame, open_sequence
from surgtrack.realsense import RealSenseSource, record_sequence
from surgtrack.tracker import SurgTracker


def waits(recording: Path, work: Callable[[Frame], None]) -> tuple[int, float, float]:
    """Frames played from ``recording``, the mean seconds the caller waited for each and the mean seconds
    ``work`` took on each."""
    waited = worked = 0.0
    frames = 0
    with RealSenseSource(recording) as source:
        played = iter(source)
        while True:
            start = time.perf_counter()
            frame = next(played, None)
            if frame is None:
                break
            got = time.perf_counter()
            work(frame)
            waited += got - start
            worked += time.perf_counter() - got
            frames += 1
    return frames, waited / max(frames, 1), worked / max(frames, 1)


def tracking(first_mask: np.ndarray) -> Callable[[Frame], None]:
    """Work that tracks each frame it is given, the first registered with ``first_mask``."""
    tracker = SurgTracker(TrackerConfig(sdf=SDFConfig(enabled=False)))

    def track(frame: Frame) -> None:
        if frame.index == 0:
            tracker.register(frame, first_mask)
        else:
            tracker.track(frame)

    return track


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", type=Path)
    a = ap.parse_args()
    first_mask = open_sequence(a.sequence)[0].mask
    with tempfile.TemporaryDirectory() as tmp:
        recording = Path(tmp) / "recording.db3"
        record_sequence(a.sequence, recording)
        for name, work in (("nothing", lambda frame: None), ("tracking", tracking(first_mask))):
            frames, wait, worked = waits(recording, work)
            print(f"{name:8} between frames: {frames} frames, waited {wait * 1000:.2f} ms a frame, worked "
                  f"{worked * 1000:.2f} ms a frame")


if __name__ == "__main__":
    main()
