"""Why the frames of a run were lost, against how much of the instrument each showed: for every sequence, the lost
frames by their `reason` (track.jsonl), how many of them had a true mask of at least ``--min-pixels`` pixels (the
instrument was there to see), and the frames whose true mask has under ``--unseen`` pixels, which no tracker can
give a pose (the evaluation counts them as misses): the ADD-S / ADD AUC a run can reach at most.

    .venv/bin/python benchmarks/lost_frames.py runs/every_s0/surgtrack runs/every_s0/data
"""

from __future__ import annotations

from collections import Counter

import numpy as np
from result_runs import result_folders, results_parser

from surgtrack.io import open_sequence, read_mask, read_track_log


def main() -> None:
    ap = results_parser(__doc__.splitlines()[0])
    ap.add_argument("--min-pixels", type=int, default=150, help="a true mask this large showed the instrument")
    ap.add_argument("--unseen", type=int, default=100, help="a true mask smaller than this: nothing to track")
    a = ap.parse_args()
    print(f"| sequence | lost | by reason | lost with a true mask >= {a.min_pixels} px | "
          f"true mask < {a.unseen} px | AUC at most |")
    print("|---|---|---|---|---|---|")
    reasons: Counter[str] = Counter()
    ceilings, lost_all, shown_all = [], 0, 0
    for out in result_folders(a.results, "track.jsonl"):
        seq = open_sequence(a.data / out.name)
        area = {}
        for i, f in enumerate(seq.ids):
            path = seq.mask_path(i)
            area[f] = int(np.count_nonzero(read_mask(path))) if path.exists() else 0
        lost = [r for r in read_track_log(out) if r["status"] == "lost"]
        why = Counter(r.get("reason", "?") for r in lost)
        shown = sum(area[r["frame"]] >= a.min_pixels for r in lost)
        unseen = sum(n < a.unseen for n in area.values())
        ceiling = 100.0 * (1 - unseen / len(area))
        reasons.update(why)
        ceilings.append(ceiling)
        lost_all += len(lost)
        shown_all += shown
        text = ", ".join(f"{k} {n}" for k, n in why.most_common()) or "-"
        print(f"| {out.name} | {len(lost)} | {text} | {shown} | {unseen} | {ceiling:.1f} |")
    text = ", ".join(f"{k} {n}" for k, n in reasons.most_common()) or "-"
    print(f"| all | {lost_all} | {text} | {shown_all} | | mean {np.mean(ceilings):.2f} |")


if __name__ == "__main__":
    main()
