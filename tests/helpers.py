"""Helpers shared by test modules (pytest puts this folder on sys.path)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from surgtrack.io import ResultWriter


def write_result(out: Path, poses: dict[str, np.ndarray], mesh: trimesh.Trimesh | None = None) -> Path:
    """A result folder as `surgtrack track` writes it: the given poses, and the mesh when given."""
    with ResultWriter(out) as writer:
        for frame_id, T in poses.items():
            writer.write(frame_id, T, {"status": "tracked"})
        if mesh is not None:
            writer.write_mesh(mesh)
    return out
