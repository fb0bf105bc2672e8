"""Time the Instrument SDF's full fit on the keyframes a tracker collects over a whole sequence.

Tracks SEQ with its per-frame masks (the SDF off while tracking, so the keyframes do not depend on fit timing),
then fits a fresh field on every keyframe in the memory pool, as `SurgTracker.mesh()` does at the end of a run, in
the box `register` gives it. Prints the seconds of the TSDF initialisation and of the fit, and the Chamfer distance
of the mesh to the ground-truth surface the video shows (DESIGN.md section 4, as `surgtrack eval` measures it).

    .venv/bin/python benchmarks/sdf_fit_sequence.py SEQ [--threads 1] [--refine-poses]

With --refine-poses the keyframe poses are refined jointly with the field (`sdf.refine_poses`).
"""

from __future__ import annotations

import argparse
import os
import time

import torch

from surgtrack.config import TrackerConfig
from surgtrack.geometry import inv_T
from surgtrack.io import open_sequence
from surgtrack.metrics import chamfer_cm
from surgtrack.preprocess import preprocess
from surgtrack.tracker import SurgTracker, new_field


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("seq", help="a sequence with per-frame masks and ground truth (e.g. from `surgtrack synth`)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (1: see BackgroundFitter)")
    ap.add_argument("--refine-poses", action="store_true", help="refine the keyframe poses jointly with the field")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    seq = open_sequence(args.seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    cfg.sdf.refine_poses = args.refine_poses
    tracker = SurgTracker(cfg)
    first = seq[0]
    pose0 = tracker.register(first, first.mask)
    t = time.perf_counter()
    for i in range(1, len(seq)):
        tracker.track(seq[i], seq[i].mask)
    t_track = time.perf_counter() - t
    views = tracker.views()
    sdf = new_field(cfg.sdf, preprocess(first, first.mask, cfg.preprocess), pose0[:3, 3])
    t = time.perf_counter()
    sdf.init_tsdf(views)
    t_init = time.perf_counter() - t
    report = sdf.fit(views)
    mesh = tracker.surface(sdf)
    gt0 = seq.gt_poses()[first.id]
    cd = chamfer_cm(mesh, inv_T(gt0) @ pose0, seq.gt_visible_points())
    print(f"{seq.root.name}: {len(seq)} frames tracked in {t_track:.1f} s (not counted), {len(views)} keyframes, "
          f"grid {sdf.grid.shape} voxel {cfg.sdf.voxel_size * 1e3:.1f} mm, device {sdf.device}, "
          f"torch threads {torch.get_num_threads()}")
    print(f"rays: {report['rays'][0]} instrument, {report['rays'][1]} other; iterations {cfg.sdf.iterations}, "
          f"refine_poses {cfg.sdf.refine_poses}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    print(f"init_tsdf {t_init:.2f} s, fit {report['seconds']:.2f} s, total {t_init + report['seconds']:.2f} s; "
          f"converged {sdf.converged}; mesh {len(mesh.faces)} faces, CD {cd:.2f} cm")


if __name__ == "__main__":
    main()
