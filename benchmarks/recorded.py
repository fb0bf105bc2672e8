"""What the call-by-call benchmarks (`free_space_cost.py`, `ransac_cost.py`) share: a tracking run with one
function's calls recorded, and the fastest of several timed replays of them."""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from surgtrack.config import TrackerConfig
from surgtrack.io import open_sequence
from surgtrack.pipeline import track_sequence


def sequences(data: Path) -> list[Path]:
    """The sequence folders in DATA, by name."""
    return sorted(p for p in data.iterdir() if p.is_dir())


def track_recording(seq_root: Path, owner: object, name: str, record: Callable) -> tuple[int, float]:
    """Track the sequence with per-frame masks and the SDF off (the run repeats exactly and no worker shares the
    cores) while ``owner.name`` is replaced by ``record(original, *args)``; returns frames and seconds."""
    original = getattr(owner, name)
    setattr(owner, name, lambda *a, **k: record(original, *a, **k))
    try:
        with tempfile.TemporaryDirectory() as out:
            s = track_sequence(open_sequence(seq_root), out, TrackerConfig.from_dict({"sdf": {"enabled": False}}))
    finally:
        setattr(owner, name, original)
    return s.frames, s.seconds


def fastest(fn: Callable, args: list[tuple], repeats: int) -> float:
    """The fastest of ``repeats`` timed passes of ``fn(*a)`` over every ``a`` in ``args``, seconds."""
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for a in args:
            fn(*a)
        best = min(best, time.perf_counter() - t)
    return best
