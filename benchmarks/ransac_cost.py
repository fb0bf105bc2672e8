"""What RANSAC (`ransac.ransac_pose`, eq. 5) costs tracking, per frame, measured call by call.

    .venv/bin/python benchmarks/ransac_cost.py DATA [--repeats N] [--calls FILE]

DATA holds rendered sequences, one folder each (e.g. the ``data/`` folder that ``surgtrack bench --frames 100``
writes). Each sequence is tracked once with per-frame masks and the SDF off, and every `ransac_pose` call the tracker
makes (the coarse pose, the feature edges of the posture graph, re-localisation) is recorded with its matches and
the state of the random generator it was given. The calls are then replayed ``--repeats`` times and the fastest
replay is kept (`recorded.fastest`). With ``--calls FILE`` the recorded calls are written to FILE, or read
from it when it exists, so that two versions of the code can be timed on the same calls. Prints, per sequence, the
calls a frame, their median number of matches, milliseconds a call and a frame, and the tracking's own
milliseconds a frame (of the recording run).
"""

from __future__ import annotations

import argparse
import pickle
from pathlib import Path

import numpy as np
from recorded import fastest, sequences, track_recording

import surgtrack.tracker
from surgtrack.ransac import ransac_pose


def recorded_calls(seq_root: Path) -> tuple[list, int, float]:
    """Track the sequence (SDF off) and return its `ransac_pose` calls, frames and seconds."""
    calls = []

    def record(pose, src, dst, rcfg, rng, src_n=None, dst_n=None):  # noqa: ANN001, ANN202 - a transparent wrapper
        calls.append((np.array(src), np.array(dst), rcfg, rng.bit_generator.state,
                      None if src_n is None else np.array(src_n), None if dst_n is None else np.array(dst_n)))
        return pose(src, dst, rcfg, rng, src_n, dst_n)

    return calls, *track_recording(seq_root, surgtrack.tracker, "ransac_pose", record)


def replay(src, dst, rcfg, state, src_n, dst_n):  # noqa: ANN001, ANN201 - the recorded arguments
    rng = np.random.default_rng()
    rng.bit_generator.state = state
    return ransac_pose(src, dst, rcfg, rng, src_n, dst_n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--calls", type=Path, help="write the recorded calls here, or read them when the file exists")
    args = ap.parse_args()
    if args.calls is not None and args.calls.exists():
        recorded = pickle.loads(args.calls.read_bytes())
    else:
        recorded = {root.name: recorded_calls(root)
                    for root in sequences(args.data)}
        if args.calls is not None:
            args.calls.write_bytes(pickle.dumps(recorded))
    print(f"{'sequence':<18} {'calls/frame':>11} {'matches':>7} {'ms/call':>7} {'RANSAC ms/frame':>15} "
          f"{'tracking ms/frame':>17}")
    totals = np.zeros(4)
    for name, (calls, frames, seconds) in recorded.items():
        t = fastest(replay, calls, args.repeats)
        matches = np.median([len(c[0]) for c in calls]) if calls else 0
        print(f"{name:<18} {len(calls) / frames:11.1f} {matches:7.0f} {1e3 * t / max(len(calls), 1):7.2f} "
              f"{1e3 * t / frames:15.1f} {1e3 * seconds / frames:17.1f}", flush=True)
        totals += (frames, t, seconds, len(calls))
    frames, t, seconds, n = totals
    print(f"{'all':<18} {n / frames:11.1f} {'':>7} {1e3 * t / max(n, 1):7.2f} {1e3 * t / frames:15.1f} "
          f"{1e3 * seconds / frames:17.1f}")


if __name__ == "__main__":
    main()
