"""Where a tracked run's AUC goes: per sequence, the frames whose ADD-S lies within 2 cm, from 2 to 6 cm and beyond
6 cm (a frame beyond 6 cm adds under 0.4 of a well-tracked frame to the ADD-S AUC: the instrument is as good as
lost, yet reported tracked), the frames reported lost, and each re-localisation with the ADD-S of the pose it gave.

    .venv/bin/python benchmarks/error_bands.py RESULTS DATA

RESULTS holds one result folder a sequence (OUT/track.jsonl, OUT/ob_in_cam/), e.g. ``bench_out/surgtrack``;
DATA the rendered sequences of the same names, e.g. ``bench_out/data``. Prints a Markdown table.
"""

from __future__ import annotations

import numpy as np
from result_runs import result_runs

from surgtrack.io import read_track_log
from surgtrack.metrics import evaluate

BANDS = (0.02, 0.06)  # m, ADD-S band edges


def main() -> None:
    print("| sequence | ADD-S < 2 cm | 2-6 cm | > 6 cm | lost | re-localised at frame (ADD-S, cm) |")
    print("|---|---|---|---|---|---|")
    for out, seq, _, _ in result_runs(__doc__.splitlines()[0], "track.jsonl"):
        adds = evaluate(out, seq)["errors"]["add_s"]
        e = np.array([np.inf if v is None else v for v in adds.values()])
        status = read_track_log(out)
        found = [f"{i} ({100 * adds[s['frame']]:.1f})" for i, s in enumerate(status)
                 if s["status"] == "relocalised" and adds.get(s["frame"]) is not None]
        counts = (np.sum(e < BANDS[0]), np.sum((e >= BANDS[0]) & (e < BANDS[1])),
                  np.sum(np.isfinite(e) & (e >= BANDS[1])), np.sum(~np.isfinite(e)))
        print(f"| {out.name} | " + " | ".join(str(int(c)) for c in counts) + f" | {', '.join(found) or '-'} |")


if __name__ == "__main__":
    main()
