"""What the speed benchmarks share: for the call-by-call ones (`free_space_cost.py`, `ransac_cost.py`) a tracking run
with one function's calls recorded and the fastest of several timed replays of them; for the whole-run ones
(`sdf_speed.py`, `speed_vs_revision.py`, `threads_speed.py`) runs of two arms in the order A B B A, each in a
fresh process where the script asks for one, and their table."""

from __future__ import annotations

import json
import subprocess
import sys
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


def abba(seqs: list[Path], run: Callable[[str, Path], tuple[int, float]], repeats: int) -> None:
    """Run each sequence ``repeats`` times in the order A B B A, ``run(arm, seq) -> (frames, seconds)``, so that a
    drift of the machine's speed falls on both arms alike; print each sequence's frames/s for A and B and the
    totals."""
    totals = {arm: [0, 0.0] for arm in "AB"}
    print(f"{'sequence':<18} {'A frames/s':>10} {'B frames/s':>10}  B/A")
    for seq in seqs:
        per = {arm: [0, 0.0] for arm in "AB"}
        for _ in range(repeats):
            for arm in "ABBA":
                frames, seconds = run(arm, seq)
                per[arm][0] += frames
                per[arm][1] += seconds
        fps = {arm: n / t for arm, (n, t) in per.items()}
        print(f"{seq.name:<18} {fps['A']:10.2f} {fps['B']:10.2f}  {fps['B'] / fps['A']:.3f}", flush=True)
        for arm in totals:
            totals[arm][0] += per[arm][0]
            totals[arm][1] += per[arm][1]
    fps = {arm: n / t for arm, (n, t) in totals.items()}
    print(f"{'all':<18} {fps['A']:10.2f} {fps['B']:10.2f}  {fps['B'] / fps['A']:.3f}")


# A whole tracking run for `child_run`; argv[1]: the sequence; the default configuration, or that of the JSON file an
# argument --config=PATH names; per-frame masks, or the first frame's mask only with an argument --first-mask-only.
TRACK_RUN = """
import json, sys, tempfile
from pathlib import Path
from surgtrack.config import TrackerConfig
from surgtrack.io import open_sequence
from surgtrack.pipeline import track_sequence
named = [a.split("=", 1)[1] for a in sys.argv if a.startswith("--config=")]
config = TrackerConfig.from_dict(json.loads(Path(named[0]).read_text())) if named else None
with tempfile.TemporaryDirectory() as out:
    s = track_sequence(open_sequence(sys.argv[1]), out, config, first_mask_only="--first-mask-only" in sys.argv)
print(json.dumps({"frames": s.frames, "seconds": s.seconds}))
"""


def child_run(code: str, args: list[str], env: dict[str, str], label: str) -> tuple[int, float]:
    """Run ``code`` in a fresh Python process with ``args`` and ``env``; it prints {"frames": n, "seconds": s} last.
    Returns (frames, seconds); a failed run stops the benchmark with its ``label`` and the end of its stderr."""
    done = subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{label} failed:\n{done.stderr[-2000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return int(result["frames"]), float(result["seconds"])
