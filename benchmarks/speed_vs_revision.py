"""Tracking speed of this checkout against the code at another git revision, measured in pairs: #5 asks that the
Instrument SDF leave tracking no slower than it was before #5 (the revision before the SDF came in is 549f558).

    .venv/bin/python benchmarks/speed_vs_revision.py DATA REV [--repeats N] [--first-mask-only] [--config C.json]

DATA holds rendered sequences, one folder each (e.g. the ``data/`` folder that ``surgtrack bench`` writes). REV is
checked out into a temporary git worktree. Each sequence is tracked with per-frame masks and each code's default
configuration (``--config``: both codes with that JSON configuration, e.g. the SDF off so that both track the same
poses and the time compares the same work; ``--first-mask-only``: the first frame's mask only, the others made by
the tracker; both codes must have that option) in the order A B B A (A: this checkout, B: REV), ``--repeats`` times,
each run in a fresh Python process with that code first on its path, so that a drift of the machine's speed falls on
both alike. Frames/s is frames over the tracking's wall-clock time as each code's ``track_sequence`` reports it
(``RunSummary.seconds``: the end-of-run mesh is not counted). Prints each sequence's frames/s for A and B and the
totals.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import tempfile
from pathlib import Path

from recorded import TRACK_RUN, abba, child_run, sequences

REPO = Path(__file__).resolve().parents[1]


def timed_run(src: Path, seq: Path, first_mask_only: bool, config: Path | None) -> tuple[int, float]:
    """(frames, tracking seconds) of one run of the code in ``src`` on ``seq``."""
    args = [str(seq)] + (["--first-mask-only"] if first_mask_only else [])
    args += [f"--config={config.resolve()}"] if config else []
    return child_run(TRACK_RUN, args, {**os.environ, "PYTHONPATH": str(src)}, f"{seq}: the run with {src}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("rev", help="git revision to compare with, e.g. 549f558")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--first-mask-only", action="store_true", help="track from the first frame's mask only")
    ap.add_argument("--config", type=Path, help="tracker configuration (JSON) for both codes; default: each its own")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "rev"
        subprocess.run(["git", "-C", str(REPO), "worktree", "add", "--detach", "-q", str(tree), args.rev], check=True)
        try:
            srcs = {"A": REPO / "src", "B": tree / "src"}
            print(f"A: {REPO} (this checkout), B: {args.rev}")
            abba(sequences(args.data), lambda arm, seq: timed_run(srcs[arm], seq, args.first_mask_only, args.config),
                 args.repeats)
        finally:
            subprocess.run(["git", "-C", str(REPO), "worktree", "remove", "--force", str(tree)], check=False)


if __name__ == "__main__":
    main()
