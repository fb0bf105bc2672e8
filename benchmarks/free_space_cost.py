"""What L_FS (`posture_graph.FreeSpace`), or L_CV (`posture_graph.Coverage`), costs tracking, per frame, measured
call by call.

    .venv/bin/python benchmarks/free_space_cost.py DATA [--repeats N] [--term coverage]

DATA holds rendered sequences, one folder each (e.g. the ``data/`` folder that ``surgtrack bench --frames 100``
writes). Each sequence is tracked once with per-frame masks, the SDF off (so the run is the same every time and no
worker shares the cores), and every L_FS evaluation the posture graph makes is recorded: the frame's mask edge
(`preprocess.MaskEdge`, built once a frame) and each Gauss-Newton iteration's `FreeSpace.residuals`. Both are then
replayed ``--repeats`` times and the fastest replay of each is kept, so a drift of the machine's speed, which
decides a whole-run comparison on a shared machine, barely touches the figure. Prints, per sequence, the L_FS
calls a frame, microseconds a call, the mask edge's milliseconds a frame and the sum, beside the tracking's own
milliseconds a frame. With ``--term coverage`` the same for L_CV: its calls, and the mask edge of the first
keyframe it looks into (built once).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from recorded import fastest, sequences, track_recording

from surgtrack.posture_graph import Coverage, FreeSpace
from surgtrack.preprocess import MaskEdge

TERMS = {"free_space": FreeSpace, "coverage": Coverage}


def recorded_calls(seq_root: Path, term: type) -> tuple[list, int, float]:
    """Track the sequence (SDF off) and return the term's calls (term, C, cfg), frames and seconds."""
    calls = []

    def record(residuals, t, C, cfg):  # noqa: ANN001, ANN202 - a transparent wrapper
        calls.append((t, C.copy(), cfg))
        return residuals(t, C, cfg)

    return calls, *track_recording(seq_root, term, "residuals", record)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--term", choices=sorted(TERMS), default="free_space")
    args = ap.parse_args()
    term = TERMS[args.term]
    name = "L_FS" if term is FreeSpace else "L_CV"
    print(f"{'sequence':<18} {'calls/frame':>11} {'us/call':>8} {'edge ms/frame':>13} {name + ' ms/frame':>13} "
          f"{'tracking ms/frame':>17}")
    totals = [0, 0.0, 0.0, 0.0]
    for root in sequences(args.data):
        calls, frames, seconds = recorded_calls(root, term)
        # the mask edge each call uses (the frame's for L_FS, the keyframe's for L_CV), each edge once
        masks = list({id(t.view.edge): (t.view.edge.mask,) for t, _, _ in calls}.values())
        t_res = fastest(term.residuals, calls, args.repeats)
        t_edge = fastest(MaskEdge.of, masks, args.repeats)
        per_call = 1e6 * t_res / max(len(calls), 1)
        print(f"{root.name:<18} {len(calls) / frames:11.1f} {per_call:8.0f} {1e3 * t_edge / frames:13.2f} "
              f"{1e3 * (t_res + t_edge) / frames:13.2f} {1e3 * seconds / frames:17.1f}", flush=True)
        for i, v in enumerate((frames, t_res + t_edge, seconds, len(calls))):
            totals[i] += v
    frames, t_fs, seconds, n = totals
    print(f"{'all':<18} {n / frames:11.1f} {'':>8} {'':>13} {1e3 * t_fs / frames:13.2f} {1e3 * seconds / frames:17.1f}")


if __name__ == "__main__":
    main()
