"""Which term of the posture graph moves one frame's solve: the sequence is tracked up to frame N as `surgtrack
track` tracks it, and frame N's first solve (eqs. 7-11, from its coarse pose) is repeated with each term switched
off in turn, each from the same start, before the run goes on as it was.

    .venv/bin/python benchmarks/term_pull.py DATA/SEQ N [--first-mask-only] [--config C.json]

Printed: the coarse pose's and each solve's move from the last tracked pose (degrees, mm), and L_FS at the start
and the end of the full solve (`posture_graph.FreeSpace`: points the frame saw past, the sum and the largest of
their distances to the mask in mm). Without ground truth nothing else is needed; with it, the error of each solve's
pose is printed too (ADD-S and ADD over the evaluation's model points, mm). The default configuration is the SDF off,
whose poses do not depend on timing.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np
from result_runs import tracker_config

from surgtrack.geometry import inv_T, rotation_angle_deg
from surgtrack.io import open_sequence
from surgtrack.metrics import add_errors, adds_errors, model_points
from surgtrack.tracker import SurgTracker

SWITCHED = {"every term": {}, "L_FS off": {"w_fs": 0.0}, "L_CV off": {"w_cv": 0.0}, "L_2D off": {"w_p": 0.0},
            "L_3D off": {"w_f": 0.0}, "prior off": {"w_m": 0.0}, "prior x100": {"w_m": 100.0},
            "1 step": {"iterations": 1, "given_mask_iterations": 1}}


def move(pose: np.ndarray, ref: np.ndarray) -> str:
    d = inv_T(ref) @ pose
    return f"{rotation_angle_deg(d[:3, :3]):6.1f} deg {np.linalg.norm(d[:3, 3]) * 1e3:6.1f} mm"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", type=Path)
    ap.add_argument("frame", type=int)
    ap.add_argument("--first-mask-only", action="store_true")
    ap.add_argument("--config", type=Path, help="tracker configuration (JSON); default: the SDF off")
    a = ap.parse_args()
    seq = open_sequence(a.seq)
    if not 1 <= a.frame < len(seq):
        ap.error(f"frame must lie in 1..{len(seq) - 1}")
    cfg = tracker_config(a.config)
    tracker = SurgTracker(cfg)
    gt = seq.gt_poses()
    pts = model_points(seq.gt_visible_points(), seq.gt_model()) if gt else None
    first = seq[0]
    align = inv_T(tracker.register(first, first.mask)) @ gt[first.id] if gt else None  # as `surgtrack eval` aligns
    solve, state = tracker._optimise, {"frame": -1, "done": False}

    def error(pose: np.ndarray, truth: np.ndarray) -> str:
        adds, add = adds_errors([pose @ align], [truth], pts)[0], add_errors([pose @ align], [truth], pts)[0]
        return f"  ADD-S {adds * 1e3:6.1f} mm  ADD {add * 1e3:6.1f} mm"

    def compared(node, edges, candidate=False, obs=None):
        if state["frame"] != a.frame or state["done"] or candidate:
            return solve(node, edges, candidate, obs)
        state["done"] = True
        last, start, base = tracker.recent[-1].pose, node.pose.copy(), tracker.cfg
        truth = gt.get(seq.ids[a.frame]) if gt and pts is not None else None  # scored when it can be
        print(f"frame {seq.ids[a.frame]} ({'no mask' if obs is not None and not obs.mask_given else 'its mask'}), "
              f"moves from the last tracked pose:")
        print(f"  {'coarse pose':12s} {move(start, last)}" + (error(start, truth) if truth is not None else ""))
        for name, change in SWITCHED.items():
            tracker.cfg = replace(base, graph=replace(base.graph, **change))
            node.pose = start.copy()
            pose = solve(node, list(edges), candidate, obs)
            print(f"  {name:12s} {move(pose, last)}" + (error(pose, truth) if truth is not None else ""))
            if name == "every term" and obs is not None:
                fs = tracker._free_space(node, obs, base.graph)
                for when, at in (("start", start), ("end", pose)):
                    r = fs[1].view.seen_past(fs[1].points, inv_T(at), base.graph)[1] if fs is not None else []
                    print(f"    L_FS at the {when}: {len(r)} points seen past, sum {np.sum(r) * 1e3:.1f} mm, "
                          f"largest {np.max(r, initial=0) * 1e3:.1f} mm")
        tracker.cfg = base
        node.pose = start
        return solve(node, edges, candidate, obs)

    tracker._optimise = compared
    for i in range(1, a.frame + 1):
        state["frame"] = i
        f = seq[i]
        result = tracker.track(f, None if a.first_mask_only else f.mask)
    print(f"frame {seq.ids[a.frame]}: {result.status}")


if __name__ == "__main__":
    main()
