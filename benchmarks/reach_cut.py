"""What the bound on a predicted mask's reach across the shaft (`preprocess.predicted_mask_across`) cuts at the
true pose: of the instrument, and of what lies beside it at its depth.

    .venv/bin/python benchmarks/reach_cut.py DATA [MARGIN]

DATA holds rendered sequences (``surgtrack synth DATA --suite instrument3d``); MARGIN is the option's value (m,
default 0.01). For each sequence the reach comes from the first frame's preprocessed masked points
(`tracker.long_axis`). Every 30th frame from frame 10 is mapped into the first frame's camera by the ground truth, and
the bound (`masking.within_reach`, at the ground truth's pose of the first camera in frame t) is applied to
- the true mask's pixels: the instrument the bound would cut even with a perfect pose;
- the pixels in a 25-pixel ring around the true mask whose depth lies within 3 cm of the instrument's median: a
  hand, a glove or tissue at the instrument's depth, which the bound is there to keep out.
Printed: each sequence's reach and the two shares, averaged over the frames.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation

from surgtrack.config import TrackerConfig
from surgtrack.geometry import inv_T
from surgtrack.io import open_sequence
from surgtrack.masking import within_reach
from surgtrack.preprocess import preprocess
from surgtrack.tracker import long_axis


def _percent(shares: list[float]) -> str:
    """The mean of ``shares`` in percent, or "-" when no frame had any."""
    return f"{100 * np.mean(shares):.1f}" if shares else "-"


def main(data: Path, margin: float) -> None:
    cfg = TrackerConfig()
    print(f"{'sequence':16s} {'reach cm':>8s} {'instrument cut %':>17s} {'beside it cut %':>16s}")
    for folder in sorted(p for p in data.iterdir() if (p / "cam_K.txt").is_file()):
        seq = open_sequence(folder)
        gt = seq.gt_poses()
        first = seq[0]
        axis = long_axis(preprocess(first, first.mask, cfg.preprocess).points()[0])
        cut, beside = [], []
        for t in range(10, len(seq), 30):
            frame = seq[t]
            seen = frame.depth > 0
            inst = frame.mask & seen
            if inst.sum() < 50:
                continue
            ring = binary_dilation(frame.mask, iterations=25) & ~frame.mask & seen
            ring &= np.abs(frame.depth - np.median(frame.depth[inst])) < 0.03
            first_in_t = gt[frame.id] @ inv_T(gt[first.id])  # the first camera's frame, seen from camera t
            for where, out in ((inst, cut), (ring, beside)):
                if where.sum() >= 50:
                    kept = within_reach(where, frame.depth, frame.K, first_in_t, axis, margin)
                    out.append(1.0 - np.mean(kept[where]))
        print(f"{folder.name:16s} {100 * axis[2]:8.1f} {_percent(cut):>17s} {_percent(beside):>16s}")


if __name__ == "__main__":
    main(Path(sys.argv[1]), float(sys.argv[2]) if len(sys.argv) > 2 else 0.01)
