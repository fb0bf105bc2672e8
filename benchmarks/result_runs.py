"""The command line the benchmark scripts share: RESULTS (one result folder a sequence) and DATA (the rendered
sequences of the same names) for those that read results, ``--config`` for those that track."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from surgtrack.config import TrackerConfig
from surgtrack.io import Sequence, open_sequence, read_poses


def tracker_config(path: Path | None) -> TrackerConfig:
    """The configuration a tracking script runs: ``path``'s JSON, else the SDF off, whose poses do not depend on
    how fast the background fit runs."""
    return TrackerConfig.from_dict(json.loads(path.read_text()) if path else {"sdf": {"enabled": False}})


def result_runs(description: str, marker: str) -> Iterator[tuple[Path, Sequence, dict[str, np.ndarray],
                                                               dict[str, np.ndarray]]]:
    """Parse RESULTS and DATA from the command line; yield each result folder holding ``marker``, its sequence,
    the ground-truth poses and the tracked ones."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("results", type=Path)
    ap.add_argument("data", type=Path)
    a = ap.parse_args()
    for out in sorted(p for p in a.results.iterdir() if (p / marker).exists()):
        seq = open_sequence(a.data / out.name)
        yield out, seq, seq.gt_poses(), read_poses(out / "ob_in_cam")
