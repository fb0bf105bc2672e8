"""Shared test fixtures: the real data beside the repository (../shared/data)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"{SHARED_DATA}: the shared data folder must sit beside the repository")
    return SHARED_DATA


@pytest.fixture(scope="session")
def synth_seq(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short procedural synthetic sequence (30 frames, 320x240, one occluding hand) with ground truth."""
    from surgtrack.synth import SynthSpec, render_sequence

    spec = SynthSpec(instrument="rigid_endoscope", frames=30, width=320, height=240, n_occluders=1, seed=7)
    return render_sequence(spec, tmp_path_factory.mktemp("synth") / "rigid_endoscope")
