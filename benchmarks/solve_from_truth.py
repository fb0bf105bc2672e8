"""How far the posture graph's solve moves a frame's pose away from the truth: every frame is tracked with its true
pose (the first frame's alignment as `surgtrack eval` makes it), the graph solve (eqs. 7-11) is started there with
every other node at its own true pose, and its result is recorded, then replaced by the truth again. A solve that
moves the truth measures what the frame's data pull towards, not where tracking has drifted.

    .venv/bin/python benchmarks/solve_from_truth.py DATA/SEQ [--first 1] [--last 60] [--config C.json]
        [--first-mask-only]

Printed: per frame the solve's move split along the shaft as `shaft_errors.py` splits an error (the turn about the
shaft in degrees, the slide along it and the shift across it in mm) with the true turn since the frame before,
then the median and 90th percentile of each. Frames come with their mask unless ``--first-mask-only``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from result_runs import tracker_config
from shaft_errors import sequence_shaft, shaft_parts

from surgtrack.geometry import inv_T
from surgtrack.io import open_sequence
from surgtrack.tracker import SurgTracker


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--last", type=int, default=60)
    ap.add_argument("--config", type=Path, help="tracker configuration (JSON); default: the SDF off")
    ap.add_argument("--first-mask-only", action="store_true")
    a = ap.parse_args()
    seq = open_sequence(a.seq)
    gt = seq.gt_poses()
    cfg = tracker_config(a.config)
    tracker = SurgTracker(cfg)
    first = seq[0]
    M = inv_T(gt[first.id]) @ tracker.register(first, first.mask)  # tracked object frame -> true object frame
    _, centre, axis, _ = sequence_shaft(seq)
    solve, frame = tracker._optimise, {}

    def from_truth(node, edges, candidate=False, obs=None):
        truth = gt[frame["id"]] @ M
        node.pose = truth.copy()
        moved = solve(node, edges, candidate, obs)
        frame.setdefault("moves", shaft_parts(inv_T(gt[frame["id"]]) @ moved @ inv_T(M), centre, axis))
        return truth

    tracker._optimise = from_truth
    rows = []
    print("frame   turn deg  slide mm  across mm  true turn deg")
    for i in range(1, min(a.last, len(seq) - 1) + 1):
        f = seq[i]
        frame.clear()
        frame["id"] = f.id
        tracker.track(f, None if a.first_mask_only else f.mask)
        if i < a.first or "moves" not in frame:
            continue
        turn, along, across = frame["moves"]
        true_turn = shaft_parts(inv_T(gt[seq.ids[i - 1]]) @ gt[f.id], centre, axis)[0]
        rows.append((np.degrees(turn), along * 1e3, across * 1e3))
        print(f"{f.id}  {rows[-1][0]:8.2f}  {rows[-1][1]:8.2f}  {rows[-1][2]:9.2f}  {np.degrees(true_turn):13.2f}")
    if rows:
        r = np.abs(np.array(rows))
        print("median |move|: turn {:.2f} deg, slide {:.2f} mm, across {:.2f} mm".format(*np.median(r, axis=0)))
        print("p90    |move|: turn {:.2f} deg, slide {:.2f} mm, across {:.2f} mm".format(*np.percentile(r, 90, axis=0)))


if __name__ == "__main__":
    main()
