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

from recorded import abba, sequences

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

    def run(arm: str, root: Path) -> tuple[int, float]:
        with tempfile.TemporaryDirectory() as out:
            s = track_sequence(open_sequence(root), out, configs[arm])
        return s.frames, s.seconds

    abba(sequences(args.data), run, args.repeats)


if __name__ == "__main__":
    main()
