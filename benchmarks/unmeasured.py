"""What track.jsonl's ``unmeasured`` says against the truth: per sequence, the share of posed frames reporting a turn
or a slide their data left free, how far a reported turn's axis lies from the instrument's shaft, and how much the
error's turn about the shaft changes on frames that report it and on frames that do not.

    .venv/bin/python benchmarks/unmeasured.py RESULTS DATA

RESULTS holds one result folder a sequence (OUT/track.jsonl, OUT/ob_in_cam/), e.g. ``bench_out/surgtrack``; DATA
the rendered sequences of the same names. The shaft is `shaft_errors.py`'s, carried into the tracker's object frame
by the first frame's alignment (`surgtrack eval`'s). The error's turn step of frame j is the change of the error's
twist about the shaft from the posed frame before (consecutive frames only): what that frame's solve added to the
turn, right or wrong. Prints a Markdown table.
"""

from __future__ import annotations

import numpy as np
from result_runs import result_runs
from shaft_errors import aligned_run, sequence_shaft, shaft_parts

from surgtrack.geometry import inv_T
from surgtrack.io import read_track_log


def _median(x: list[float]) -> str:
    return f"{np.median(x):.2f}" if x else "-"


def main() -> None:
    print("| sequence | posed frames | turn unmeasured | slide unmeasured | reported turn's axis off the shaft, "
          "median deg | error's turn step, median deg: turn unmeasured / measured |")
    print("|---|---|---|---|---|---|")
    for out, seq, gt, est in result_runs(__doc__.splitlines()[0], "track.jsonl"):
        ids, aligned = aligned_run(seq, gt, est)
        _, centre, axis, _ = sequence_shaft(seq)
        first = next(i for i in ids if i in aligned)
        shaft = (inv_T(est[first]) @ aligned[first])[:3, :3] @ axis  # the shaft in the tracker's object frame
        log = {s["frame"]: s for s in read_track_log(out)}
        posed = [i for i in ids if i in aligned and "unmeasured" in log.get(i, {})]
        kinds = {i: [k for u in log[i]["unmeasured"] for k in u] for i in posed}
        off = [np.degrees(np.arccos(min(1.0, abs(float(np.dot(u["turn"], shaft))))))
               for i in posed for u in log[i]["unmeasured"] if "turn" in u]
        twist = {i: np.degrees(shaft_parts(inv_T(gt[i]) @ aligned[i], centre, axis)[0]) for i in posed}
        steps: dict[bool, list[float]] = {True: [], False: []}
        for a, b in zip(ids, ids[1:], strict=False):
            if a in twist and b in twist:
                d = (twist[b] - twist[a] + 180.0) % 360.0 - 180.0
                steps["turn" in kinds[b]].append(abs(d))
        n = len(posed)
        share = {k: 100 * sum(k in v for v in kinds.values()) / max(n, 1) for k in ("turn", "slide")}
        print(f"| {out.name} | {n} | {share['turn']:.0f} % | {share['slide']:.0f} % | {_median(off)} | "
              f"{_median(steps[True])} / {_median(steps[False])} |")


if __name__ == "__main__":
    main()
