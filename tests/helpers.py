"""Helpers shared by test modules (pytest puts this folder on sys.path)."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import trimesh

from surgtrack.cli import main
from surgtrack.config import TrackerConfig
from surgtrack.io import ResultWriter, Sequence
from surgtrack.tracker import SurgTracker

SURGTRACK = Path(sys.executable).with_name("surgtrack")


def surgtrack(*args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess:
    """Run the installed ``surgtrack`` entry point with these arguments, capturing its output."""
    if not SURGTRACK.is_file():
        pytest.fail(f"{SURGTRACK}: the surgtrack entry point is not installed beside the interpreter")
    return subprocess.run([str(SURGTRACK), *map(str, args)], capture_output=True, text=True, timeout=timeout)


def surgtrack_here(*args: str | Path) -> subprocess.CompletedProcess:
    """The entry point's `main` run in this process with these arguments, its output captured, as `surgtrack`
    captures the installed entry point's: error paths and short runs without an interpreter's start-up."""
    out, err, code = io.StringIO(), io.StringIO(), 0
    argv = ["surgtrack", *map(str, args)]
    with mock.patch.object(sys, "argv", argv), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main()
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else int(e.code is not None)
    return subprocess.CompletedProcess(argv, code, out.getvalue(), err.getvalue())


def assert_one_line_error(run: subprocess.CompletedProcess, *fragments: str) -> str:
    """A run that stopped with exit status 2 and one ``surgtrack: error:`` line holding every fragment; the line."""
    assert run.returncode == 2, run.stdout + run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("surgtrack: error: "), run.stderr
    assert "Traceback" not in run.stderr + run.stdout
    for f in fragments:
        assert f in lines[0], lines[0]
    return lines[0]


def write_result(out: Path, poses: dict[str, np.ndarray], mesh: trimesh.Trimesh | None = None) -> Path:
    """A result folder as `surgtrack track` writes it: the given poses, and the mesh when given."""
    with ResultWriter(out) as writer:
        for frame_id, T in poses.items():
            writer.write(frame_id, T, {"status": "tracked"})
        if mesh is not None:
            writer.write_mesh(mesh)
    return out


def tracked(seq: Sequence, cfg: TrackerConfig, frames: int) -> SurgTracker:
    """A tracker registered on the sequence's first frame and run on the next ``frames - 1``, with their masks."""
    tracker = SurgTracker(cfg)
    tracker.register(seq[0], seq[0].mask)
    for i in range(1, frames):
        tracker.track(seq[i], seq[i].mask)
    return tracker
