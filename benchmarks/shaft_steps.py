"""One tracked sequence frame by frame, split along its shaft: each step's true and tracked motion, and the error.

    .venv/bin/python benchmarks/shaft_steps.py RESULT SEQUENCE [--first F] [--last L] [--every N]

RESULT is one result folder (RESULT/ob_in_cam/), SEQUENCE the rendered sequence it tracked. The tracked poses are
aligned at the first frame as `surgtrack eval` aligns them, and the shaft is `shaft_errors.py`'s (the rendered
instrument's own axis, else the first principal axis of the evaluation's model points). For each step of N frames
from F to L: the turn about the shaft (degrees) and the slide along it (cm) of the true motion gt_i^-1 gt_j and of
the tracked motion, then the error's turn, slide and shift across the shaft at frame j. Where `shaft_errors.py` says
what the turn and the slide cost a run, this says at which frames they came in; a step that is tracked much larger
than it truly was, then carried on for a few frames, is the constant-velocity prediction carrying a wrong step.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from shaft_errors import aligned_run, sequence_shaft, shaft_parts

from surgtrack.geometry import inv_T
from surgtrack.io import open_sequence, read_poses


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result", type=Path)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--last", type=int, default=None)
    ap.add_argument("--every", type=int, default=1)
    a = ap.parse_args()
    seq = open_sequence(a.sequence)
    gt, est = seq.gt_poses(), read_poses(a.result / "ob_in_cam")
    ids, tracked = aligned_run(seq, gt, est)
    _, centre, axis, _ = sequence_shaft(seq)
    last = len(ids) - 1 if a.last is None else min(a.last, len(ids) - 1)
    print(f"{'frame':>8} {'true turn':>10} {'tracked':>8} {'true slide':>11} {'tracked':>8}   "
          f"{'error: turn':>11} {'slide':>6} {'across':>7}")
    for k in range(a.first + a.every, last + 1, a.every):
        i, j = ids[k - a.every], ids[k]
        if i not in tracked or j not in tracked:
            print(f"{j:>8} lost")
            continue
        true_turn, true_slide, _ = shaft_parts(inv_T(gt[i]) @ gt[j], centre, axis)
        turn, slide, _ = shaft_parts(inv_T(tracked[i]) @ tracked[j], centre, axis)
        err_turn, err_slide, across = shaft_parts(inv_T(gt[j]) @ tracked[j], centre, axis)
        print(f"{j:>8} {np.degrees(true_turn):10.1f} {np.degrees(turn):8.1f} {true_slide * 100:11.2f} "
              f"{slide * 100:8.2f}   {np.degrees(err_turn):11.1f} {err_slide * 100:6.2f} {across * 100:7.2f}")


if __name__ == "__main__":
    main()
