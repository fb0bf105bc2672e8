"""Where #6's gap sits: each sequence's share of the suite's mean ADD-S and ADD AUC lost from a run with every
frame's mask (EVERY) to one with the first mask only (FIRST), both `surgtrack bench` output folders of the same
suite and render. A sequence's share is its own loss over the number of sequences; the shares add up to the gap.

    .venv/bin/python benchmarks/mask_gap.py runs/every_s0 runs/first_s0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def sequences(run: Path) -> tuple[dict[str, dict], dict]:
    """Per-sequence figures and the means of surgtrack's rows in RUN/bench.json."""
    results = json.loads((run / "bench.json").read_text())["methods"]["surgtrack"]
    return results["sequences"], results


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("every", type=Path, help="bench output folder, every frame's mask")
    ap.add_argument("first", type=Path, help="bench output folder, the first mask only")
    a = ap.parse_args()
    (every, mean_e), (first, mean_f) = sequences(a.every), sequences(a.first)
    if set(every) != set(first):
        raise SystemExit(f"{a.first}: other sequences than {a.every}")
    n = len(every)
    shares = sorted(((name, (every[name]["add_s_auc"] - first[name]["add_s_auc"]) / n,
                      (every[name]["add_auc"] - first[name]["add_auc"]) / n) for name in every),
                    key=lambda row: -row[1])
    print(f"{'sequence':<18} {'every mask':>15} {'first mask':>15} {'ADD-S share':>11} {'ADD share':>9}")
    for name, s, d in shares:
        e, f = every[name], first[name]
        print(f"{name:<18} {e['add_s_auc']:7.2f}/{e['add_auc']:6.2f} {f['add_s_auc']:7.2f}/{f['add_auc']:6.2f} "
              f"{s:11.2f} {d:9.2f}")
    print(f"{'mean':<18} {mean_e['add_s_auc']:7.2f}/{mean_e['add_auc']:6.2f} "
          f"{mean_f['add_s_auc']:7.2f}/{mean_f['add_auc']:6.2f} {sum(r[1] for r in shares):11.2f} "
          f"{sum(r[2] for r in shares):9.2f}")


if __name__ == "__main__":
    main()
