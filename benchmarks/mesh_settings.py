"""Chamfer distance of the end-of-run mesh for each `seen_dist` and `keep_frac` of `InstrumentSDF.mesh`.

Tracks each sequence under DATA with its per-frame masks and the default config (`--seed` S) as `surgtrack track`
does (`track_sequence`, whose end-of-run mesh makes the final field), then meshes that one field at every setting
and scores each mesh as `surgtrack eval` does (DESIGN.md section 4). The field is the same for every setting of a
sequence, so only the setting differs within a run; the field itself depends on the background fit's timing (what
share of the cores it gets), and a sequence's CD can move by a few tenths of a centimetre between runs: compare
settings within one.

    .venv/bin/python benchmarks/mesh_settings.py DATA [--seed 0] [--seen 1 1.5 2 3] [--keep 0 0.05 0.1 0.2]

DATA is a folder of rendered sequences (e.g. the instrument suite's `data/`). `--seen` is in voxels (`sdf.mesh_seen`).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from surgtrack.config import TrackerConfig
from surgtrack.geometry import inv_T
from surgtrack.io import open_sequence, read_poses
from surgtrack.metrics import chamfer_cm
from surgtrack.pipeline import track_sequence
from surgtrack.tracker import SurgTracker


def sequence_cd(path: Path, seed: int, seen: list[float], keep: list[float]) -> dict[tuple[float, float], float]:
    """CD (cm) of one sequence's final field meshed at every (seen, keep) setting; inf for an empty mesh."""
    seq = open_sequence(path)
    cfg = TrackerConfig.from_dict({"seed": seed})
    tracker = SurgTracker(cfg)
    with tempfile.TemporaryDirectory() as out:  # the run as `surgtrack track` makes it, its mesh the final field's
        track_sequence(seq, out, cfg, tracker=tracker)
        pose0 = read_poses(Path(out) / "ob_in_cam")[seq.ids[0]]
    psi = tracker.fitted_field()  # the latest field lengthened along the shaft and refitted on every keyframe
    to_gt = inv_T(seq.gt_poses()[seq.ids[0]]) @ pose0
    surface = seq.gt_visible_points()
    out = {}
    for s in seen:
        for k in keep:
            mesh = psi.mesh(keep_frac=k, seen=tracker.model_points, seen_dist=s * cfg.sdf.voxel_size)
            out[s, k] = chamfer_cm(mesh, to_gt, surface) if len(mesh.faces) else float("inf")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path, help="a folder of sequences with per-frame masks and ground truth")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--seen", type=float, nargs="+", default=[1.0, 1.5, 2.0, 3.0], help="voxels")
    ap.add_argument("--keep", type=float, nargs="+", default=[0.0, 0.05, 0.1, 0.2])
    args = ap.parse_args()
    paths = sorted(p for p in args.data.iterdir() if (p / "gt").is_dir())
    if not paths:
        raise SystemExit(f"{args.data}: no sequence with ground truth (SEQ/gt/) in it")
    rows = {}
    for p in paths:
        rows[p.name] = sequence_cd(p, args.seed, args.seen, args.keep)
        print(p.name, " ".join(f"{s:g}/{k:g}: {v:.2f}" for (s, k), v in rows[p.name].items()), flush=True)
    print(f"\nmean CD (cm) over {len(rows)} sequences, seed {args.seed}; rows seen_dist (voxels), columns keep_frac")
    print("seen \\ keep " + " ".join(f"{k:>7g}" for k in args.keep))
    for s in args.seen:
        means = [np.mean([r[s, k] for r in rows.values()]) for k in args.keep]
        print(f"{s:>11g} " + " ".join(f"{m:7.3f}" for m in means))


if __name__ == "__main__":
    main()
