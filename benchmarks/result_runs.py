"""The command line the benchmark scripts share: RESULTS (one result folder a sequence) and DATA (the rendered
sequences of the same names) for those that read results; DATA, OUT, ``--config`` and ``--only`` for those that
track a suite."""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from recorded import sequences

from surgtrack.config import TrackerConfig
from surgtrack.io import Sequence, open_sequence, read_poses


def tracker_config(path: Path | None) -> TrackerConfig:
    """The configuration a tracking script runs: ``path``'s JSON, else the SDF off, whose poses do not depend on
    how fast the background fit runs."""
    return TrackerConfig.from_dict(json.loads(path.read_text()) if path else {"sdf": {"enabled": False}})


def tracking_parser(description: str) -> argparse.ArgumentParser:
    """The arguments of a script that tracks the sequences of a suite: DATA, OUT (one result folder a sequence),
    ``--config`` (`tracker_config`) and ``--only``; the script adds its own."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("data", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--config", type=Path, help="tracker configuration (JSON); default: the SDF off")
    ap.add_argument("--only", help="comma-separated sequence names (default: every sequence in DATA)")
    return ap


def sequence_names(data: Path, only: str | None) -> list[str]:
    """``--only``'s names, else every sequence folder of DATA (`recorded.sequences`)."""
    return only.split(",") if only else [p.name for p in sequences(data)]


def results_parser(description: str) -> argparse.ArgumentParser:
    """The arguments of a script that reads results: RESULTS (one result folder a sequence) and DATA (the rendered
    sequences of the same names); the script adds its own."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("results", type=Path, help="one result folder a sequence")
    ap.add_argument("data", type=Path, help="the rendered sequences of the same names")
    return ap


def result_folders(results: Path, marker: str) -> list[Path]:
    """The result folders of RESULTS holding ``marker`` (a file or folder of a result), by name."""
    return sorted(p for p in results.iterdir() if (p / marker).exists())


def result_runs(description: str, marker: str) -> Iterator[tuple[Path, Sequence, dict[str, np.ndarray],
                                                               dict[str, np.ndarray]]]:
    """Parse RESULTS and DATA from the command line (`results_parser`); yield each result folder holding
    ``marker``, its sequence, the ground-truth poses and the tracked ones."""
    a = results_parser(description).parse_args()
    for out in result_folders(a.results, marker):
        seq = open_sequence(a.data / out.name)
        yield out, seq, seq.gt_poses(), read_poses(out / "ob_in_cam")
