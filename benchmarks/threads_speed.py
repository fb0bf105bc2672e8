"""Whole-run tracking speed with the tracker's process on one thread (OpenCV, BLAS, torch) against the default, which
lets them use every core while the SDF worker process fits on one.

    .venv/bin/python benchmarks/threads_speed.py DATA [--repeats N]

DATA holds rendered sequences, one folder each. Each sequence is tracked with per-frame masks and the default
configuration (the field fitted in its worker process) in the order A B B A (A: default threads, B: the tracker's
process on one thread: ``cv2.setNumThreads(1)``, ``torch.set_num_threads(1)`` and OMP/OpenBLAS/MKL at 1), each run in
a fresh process (the worker inherits the OMP settings; it fits on one torch thread in both arms). Prints each
sequence's frames/s for A and B and the totals (`recorded.abba`).
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from recorded import TRACK_RUN, abba, child_run, sequences

# `recorded.TRACK_RUN`, first on one thread when argv[2] is "1".
RUN = """
import sys
if sys.argv[2] == "1":
    import cv2, torch
    cv2.setNumThreads(1)
    torch.set_num_threads(1)
""" + TRACK_RUN


def run(arm: str, seq: Path) -> tuple[int, float]:
    """(frames, tracking seconds) of one run of ``arm`` on ``seq``."""
    one = arm == "B"
    env = dict(os.environ)
    if one:
        env.update(OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    return child_run(RUN, [str(seq), "1" if one else "0"], env, f"{seq}: run {arm}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--repeats", type=int, default=1)
    args = ap.parse_args()
    abba(sequences(args.data), run, args.repeats)


if __name__ == "__main__":
    main()
