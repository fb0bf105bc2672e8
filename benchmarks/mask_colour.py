"""What track.jsonl's ``colour`` tells of a pose: on the frames tracked on a mask the tracker made (first mask only),
the mean colour posterior of that mask against the frame's ADD-S error, per sequence and over the suite.

    .venv/bin/python benchmarks/mask_colour.py RESULTS DATA [--wrong 0.05] [--right 0.02]

RESULTS holds one result folder a sequence (OUT/track.jsonl, OUT/ob_in_cam/), e.g. ``bench_out/surgtrack`` of a
`surgtrack bench --first-mask-only` run; DATA the rendered sequences of the same names. A posed frame is wrong when
its ADD-S (`surgtrack eval`'s, the first pose aligned) is beyond ``--wrong`` (5 cm, the bench's "wrong %"), right
when it is within ``--right`` (2 cm). Prints two Markdown tables: by sequence the frames of each kind and their
median colour; over the suite, for each threshold, the share of each kind whose colour lies below it (what a user
who distrusts such frames would set aside), and the AUROC (the chance that a wrong frame's colour is below a right
one's). For comparison, the last row: the share whose ``confidence`` (points near the model) is below 1.
"""

from __future__ import annotations

import numpy as np
from result_runs import result_folders, results_parser

from surgtrack.io import open_sequence, read_track_log
from surgtrack.metrics import WRONG_ERR, evaluate

THRESHOLDS = (0.3, 0.4, 0.45, 0.5, 0.6)


def auroc(wrong: np.ndarray, right: np.ndarray) -> float:
    """P(a wrong frame's colour < a right frame's), ties counted half."""
    if not len(wrong) or not len(right):
        return float("nan")
    below = np.mean(wrong[:, None] < right[None, :])
    return float(below + 0.5 * np.mean(wrong[:, None] == right[None, :]))


def _median(x: np.ndarray) -> str:
    return f"{np.median(x):.2f}" if len(x) else "-"


def main() -> None:
    ap = results_parser(__doc__.splitlines()[0])
    ap.add_argument("--wrong", type=float, default=WRONG_ERR, help="ADD-S (m) beyond which a pose is wrong")
    ap.add_argument("--right", type=float, default=0.02, help="ADD-S (m) within which a pose is right")
    a = ap.parse_args()
    kinds = ("right", "between", "wrong")
    suite: dict[str, list[float]] = {k: [] for k in kinds}
    sure: dict[str, list[float]] = {k: [] for k in kinds}  # their confidence
    print("| sequence | frames with a made mask | right / between / wrong | median colour: right / between / wrong |")
    print("|---|---|---|---|")
    for out in result_folders(a.results, "track.jsonl"):
        errors = evaluate(out, open_sequence(a.data / out.name))["errors"]["add_s"]
        seen = {k: [] for k in kinds}
        for line in read_track_log(out):
            err = errors.get(line["frame"])
            if "colour" not in line or err is None:
                continue
            kind = "wrong" if err > a.wrong else "right" if err <= a.right else "between"
            seen[kind].append(line["colour"])
            sure[kind].append(line["confidence"])
        for k in kinds:
            suite[k] += seen[k]
        col = {k: np.array(v) for k, v in seen.items()}
        print(f"| {out.name} | {sum(map(len, seen.values()))} | {' / '.join(str(len(seen[k])) for k in kinds)} | "
              f"{' / '.join(_median(col[k]) for k in kinds)} |")
    col = {k: np.array(v) for k, v in suite.items()}
    print(f"\n{len(col['right'])} right, {len(col['between'])} between, {len(col['wrong'])} wrong; AUROC "
          f"{auroc(col['wrong'], col['right']):.3f}\n")
    print("| colour below | right | between | wrong |")
    print("|---|---|---|---|")
    for t in THRESHOLDS:
        shares = [f"{100 * np.mean(col[k] < t):.1f} %" if len(col[k]) else "-" for k in kinds]
        print(f"| {t} | {' | '.join(shares)} |")
    shares = [f"{100 * np.mean(np.array(sure[k]) < 1.0):.1f} %" if sure[k] else "-" for k in kinds]
    print(f"| confidence below 1 | {' | '.join(shares)} |")


if __name__ == "__main__":
    main()
