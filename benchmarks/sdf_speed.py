"""Tracking speed with the Instrument SDF and without it, measured in pairs: #5's condition that the SDF must not
slow tracking down, on a machine whose speed drifts from minute to minute.

    .venv/bin/python benchmarks/sdf_speed.py DATA [--config C.json] [--repeats N]

DATA holds rendered sequences, one folder each (e.g. the ``data/`` folder that ``surgtrack bench --frames 100``
writes). Each sequence is tracked with per-frame masks in the order A B B A (A: C.json, default the default
configuration, with the background SDF fit and L_FS; B: the same with ``sdf.enabled`` and ``graph.w_fs`` off),
``--repeats`` times, so that a drift of the machine's speed falls on both alike. Frames/s is frames over the
tracking's wall-clock time, as in ``surgtrack bench`` (the end-of-run mesh is not counted). Prints each sequence's
frames/s for A and B and the totals.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from surgtrack.config import TrackerConfig
from surgtrack.io import open_sequence
from surgtrack.pipeline import track_sequence


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--config", type=Path, help="JSON of the A runs (default: the default configuration)")
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    base = json.loads(args.config.read_text()) if args.config else {}
    off = {**base, "sdf": {**base.get("sdf", {}), "enabled": False}, "graph": {**base.get("graph", {}), "w_fs": 0.0}}
    configs = {"A": TrackerConfig.from_dict(base), "B": TrackerConfig.from_dict(off)}
    totals = {name: [0, 0.0] for name in configs}
    print(f"{'sequence':<18} {'A frames/s':>10} {'B frames/s':>10}  B/A")
    for root in sorted(p for p in args.data.iterdir() if p.is_dir()):
        seq = open_sequence(root)
        per = {name: [0, 0.0] for name in configs}
        for _ in range(args.repeats):
            for name in "ABBA":
                with tempfile.TemporaryDirectory() as out:
                    s = track_sequence(seq, out, configs[name])
                per[name][0] += s.frames
                per[name][1] += s.seconds
        fps = {name: n / t for name, (n, t) in per.items()}
        print(f"{root.name:<18} {fps['A']:10.2f} {fps['B']:10.2f}  {fps['B'] / fps['A']:.3f}", flush=True)
        for name in configs:
            totals[name][0] += per[name][0]
            totals[name][1] += per[name][1]
    fps = {name: n / t for name, (n, t) in totals.items()}
    print(f"{'all':<18} {fps['A']:10.2f} {fps['B']:10.2f}  {fps['B'] / fps['A']:.3f}")


if __name__ == "__main__":
    main()
