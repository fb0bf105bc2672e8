"""Lost and found: a full occlusion is reported lost, and tracking resumes when the instrument reappears."""

from __future__ import annotations

import json

import numpy as np
import pytest

from surgtrack.config import TrackerConfig
from surgtrack.io import open_sequence
from surgtrack.metrics import auc, evaluate
from surgtrack.pipeline import track_sequence
from surgtrack.synth import SynthSpec, render_sequence


@pytest.fixture(scope="module")
def occluded_seq(tmp_path_factory):
    """40 frames; a hand covers the whole probe from frame 15 for 10 frames while it keeps moving."""
    spec = SynthSpec(instrument="ultrasound_probe", frames=40, width=320, height=240, n_occluders=1, seed=21,
                     full_occlusions=((15, 10),), depth_range=(0.25, 0.45))
    return render_sequence(spec, tmp_path_factory.mktemp("occ") / "probe")


def test_full_occlusion_is_lost_then_relocalised(occluded_seq, tmp_path):
    seq = open_sequence(occluded_seq)
    cfg = TrackerConfig()
    cfg.sdf.enabled = False
    track_sequence(seq, tmp_path, cfg)
    status = [json.loads(x)["status"] for x in (tmp_path / "track.jsonl").read_text().splitlines()]
    visible = np.array([seq[i].mask.sum() for i in range(len(seq))])
    hidden = np.nonzero(visible == 0)[0]
    assert len(hidden) >= 10
    assert all(status[i] == "lost" for i in hidden)  # never a made-up pose while nothing is seen
    back = next(i for i in range(hidden[-1] + 1, len(seq)) if visible[i] >= 0.5 * visible[0])
    resumed = next(i for i in range(back, len(seq)) if status[i] != "lost")
    assert resumed - back <= 5
    assert status[resumed] == "relocalised"
    m = evaluate(tmp_path, seq)
    rest = [m["errors"]["add_s"][seq.ids[i]] for i in range(resumed + 2, len(seq))]
    assert auc(np.array([np.inf if e is None else e for e in rest])) >= 80
