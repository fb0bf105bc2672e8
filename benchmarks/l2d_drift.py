"""How far L_2D alone (eq. 10) moves a frame that starts at its true pose: the turn about a round shaft it leaves free.

    .venv/bin/python benchmarks/l2d_drift.py SEQ FRAME [FRAME ...] [--refs 5,10,20]

SEQ is a rendered sequence (ground-truth poses). The frame and the frames ``--refs`` before it (the keyframes, held
fixed) enter the posture graph at their true poses, with the sequence's per-frame masks and the default
preprocessing; only L_2D acts (w_f, w_fs and the motion prior w_m at 0). After 1, 3, 7 (the default), 15 and 30
Gauss-Newton iterations the frame's error is printed (`shaft_errors.shaft_parts`): its rotation, the twist of that
rotation about the shaft (`shaft_errors.sequence_shaft`: the rendered instrument's own axis, else the first
principal axis of the evaluation's model points), and the shift of the points' centroid along the shaft and across
it. A well-posed energy would leave the true pose where it is.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np
from shaft_errors import sequence_shaft, shaft_parts

from surgtrack.config import TrackerConfig
from surgtrack.geometry import inv_T, rotation_angle_deg
from surgtrack.io import open_sequence
from surgtrack.posture_graph import GraphNode, GridPoints, optimize_graph
from surgtrack.preprocess import preprocess


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq")
    ap.add_argument("frames", type=int, nargs="+")
    ap.add_argument("--refs", default="5,10,20", help="keyframes this many frames before each frame")
    args = ap.parse_args()
    seq, cfg = open_sequence(args.seq), TrackerConfig()
    gt = seq.gt_poses()
    _, centre, axis, _ = sequence_shaft(seq)

    def node(k: int, fixed: bool) -> GraphNode:
        f = seq[k]
        xyz, nrm, K = preprocess(f, f.mask, cfg.preprocess).grid(cfg.graph.depth_downscale)
        return GraphNode(gt[f.id], xyz, nrm, K, fixed, GridPoints.of(xyz, nrm))

    for k in args.frames:
        refs = [k - int(r) for r in args.refs.split(",") if k - int(r) >= 0]
        nodes = [node(k, False)] + [node(r, True) for r in refs]
        pairs = [p for j in range(1, len(nodes)) for p in ((0, j), (j, 0))]
        print(f"{seq.root.name} frame {k}, keyframes {refs}")
        for it in (1, 3, 7, 15, 30):
            g = replace(cfg.graph, w_f=0.0, w_fs=0.0, w_m=0.0, iterations=it)
            E = inv_T(gt[seq[k].id]) @ optimize_graph(nodes, [], g, pairs_2d=pairs)[0]
            turn, slide, across = shaft_parts(E, centre, axis)
            print(f"  {it:2d} iterations: rotation {rotation_angle_deg(E[:3, :3]):6.2f} deg, turn "
                  f"{np.degrees(turn):7.2f} deg, slide {slide * 1000:6.2f} mm, across {across * 1000:5.2f} mm")


if __name__ == "__main__":
    main()
