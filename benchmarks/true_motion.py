"""How fast each sequence's instrument truly moves from one frame to the next, split along its shaft.

    .venv/bin/python benchmarks/true_motion.py DATA

DATA holds rendered sequences with ground truth, e.g. ``runs/full/data``. For each pair of consecutive frames the
true motion M = gt_i^-1 gt_(i+1) (object frame) is split about the shaft `shaft_errors.py` uses, as it splits an
error: its turn about the shaft, the slide of the points' centroid along it, and the
whole rotation. Printed per sequence: the median, 95th percentile and largest turn (degrees a frame), the largest
rotation, and the 95th percentile and largest slide (mm a frame). A bound on the motion a tracker predicts or allows
should sit above these.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from shaft_errors import sequence_shaft, shaft_parts

from surgtrack.geometry import inv_T, rotation_angle_deg
from surgtrack.io import open_sequence


def main() -> None:
    for d in sorted(p for p in Path(sys.argv[1]).iterdir() if p.is_dir()):
        seq = open_sequence(d)
        gt = seq.gt_poses()
        ids = [i for i in seq.ids if i in gt]
        _, centre, axis, _ = sequence_shaft(seq)
        turn, rot, slide = [], [], []
        for a, b in zip(ids[:-1], ids[1:], strict=True):
            M = inv_T(gt[a]) @ gt[b]
            t, s, _ = shaft_parts(M, centre, axis)
            turn.append(abs(np.degrees(t)))
            slide.append(abs(s) * 1000)
            rot.append(rotation_angle_deg(M[:3, :3]))
        print(
            f"{d.name:16} turn deg median {np.median(turn):4.2f} p95 {np.percentile(turn, 95):4.2f} "
            f"max {max(turn):5.2f} | rotation max {max(rot):5.2f} | slide mm p95 {np.percentile(slide, 95):5.2f} "
            f"max {max(slide):5.2f}"
        )


if __name__ == "__main__":
    main()
