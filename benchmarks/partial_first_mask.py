"""A first mask that covers part of the instrument: are the next frames, whose masks show all of it, tracked?

    .venv/bin/python benchmarks/partial_first_mask.py DATA [--share 0.4] [--frames 30] [--config C.json] SEQ ...

Each sequence SEQ (a folder in DATA, e.g. the ``data/`` folder that ``surgtrack bench`` writes) is registered on its
first frame with the share ``--share`` of the first mask's pixels at one end of the instrument (the mask's pixels
ordered along its principal axis in the image), then tracked for ``--frames`` frames with every later frame's own
mask. Much of those frames is new to the model, as when a user's first mask or box leaves part of the instrument
out. Prints, for each sequence, each frame's status (t tracked, l lost, r re-localised) with its confidence where
below 0.9, and the frames lost.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from surgtrack.config import TrackerConfig
from surgtrack.io import open_sequence
from surgtrack.tracker import LOST, TRACKED, SurgTracker


def one_end(mask: np.ndarray, share: float) -> np.ndarray:
    """The share of ``mask``'s pixels lowest along its principal axis in the image."""
    v, u = np.nonzero(mask)
    uv = np.column_stack([u, v]).astype(float)
    uv -= uv.mean(axis=0)
    t = uv @ np.linalg.svd(uv, full_matrices=False)[2][0]
    keep = t <= np.quantile(t, share)
    out = np.zeros_like(mask)
    out[v[keep], u[keep]] = True
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--share", type=float, default=0.4)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--config", type=Path)
    args = ap.parse_args()
    cfg = TrackerConfig.from_dict(json.loads(args.config.read_text())) if args.config else TrackerConfig()
    for name in args.sequences:
        seq = open_sequence(args.data / name)
        tracker = SurgTracker(cfg)
        tracker.register(seq[0], one_end(seq[0].mask, args.share))
        marks, lost = [], 0
        for i in range(1, min(args.frames, len(seq))):
            frame = seq[i]
            result = tracker.track(frame, frame.mask)
            lost += result.status == LOST
            low = result.status != TRACKED or result.confidence < 0.9
            marks.append(result.status[0] + (f"{result.confidence:.2f}" if low else ""))
        print(f"{name} share {args.share}: lost {lost} of {len(marks)}: {' '.join(marks)}")


if __name__ == "__main__":
    main()
