"""How long a run's frames took, from the stage times each frame logs (`ms` in track.jsonl): per result root, the
frames, their summed stage time, how many took over 1 s and over 5 s, and the longest, with its stages. Stage times
count the tracker's own work, so they compare runs of one machine; two runs side by side slow each other.

    .venv/bin/python benchmarks/slow_frames.py runs/fm_s0/surgtrack runs/fm_s1/surgtrack
"""

from __future__ import annotations

import argparse
from pathlib import Path

from surgtrack.io import read_track_log


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("roots", type=Path, nargs="+", help="result roots: one folder a sequence, each with track.jsonl")
    a = ap.parse_args()
    print("| run | frames | stage time s | frames > 1 s | frames > 5 s | longest frame | its stages ms |")
    print("|---|---|---|---|---|---|---|")
    for root in a.roots:
        frames, longest, where, stages = [], 0.0, "-", {}
        for log in sorted(root.glob("*/track.jsonl")):
            for row in read_track_log(log.parent):
                ms = sum(row["ms"].values())
                frames.append(ms)
                if ms > longest:
                    longest, where, stages = ms, f"{log.parent.name}:{row['frame']}", row["ms"]
        if not frames:
            raise SystemExit(f"{root}: no */track.jsonl")
        parts = ", ".join(f"{k} {v:.0f}" for k, v in stages.items() if v >= 1)
        print(f"| {root} | {len(frames)} | {sum(frames) / 1000:.0f} | {sum(ms > 1000 for ms in frames)} | "
              f"{sum(ms > 5000 for ms in frames)} | {longest / 1000:.1f} s at {where} | {parts} |")


if __name__ == "__main__":
    main()
