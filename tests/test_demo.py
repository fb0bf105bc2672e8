"""The demo (the README's main command) end to end on a short video: every part of the report is written."""

from __future__ import annotations

import json
import re

import cv2

from surgtrack.demo import run_demo
from surgtrack.synth import SynthSpec


def test_demo_writes_the_whole_report(tmp_path):
    spec = SynthSpec(instrument="forceps", frames=16, width=320, height=240, seed=3, n_occluders=1,
                     depth_range=(0.18, 0.28))
    steps: list[str] = []
    result = run_demo(tmp_path, spec, progress=lambda stage, i, n: steps.append(stage))
    assert {"render", "track"} <= set(steps)
    report = (tmp_path / "report.md").read_text()
    assert "from the first-frame mask only" in report
    row = re.search(r"^\| ([\d.]+) \| ([\d.]+) \|", report, re.M)  # the metrics table's first row
    assert row and float(row.group(1)) == round(result["metrics"]["add_s_auc"], 2)
    assert result["metrics"]["add_s_auc"] >= 70, result["metrics"]
    log = [json.loads(x) for x in (tmp_path / "result" / "track.jsonl").read_text().splitlines()]
    turns = sum(any("turn" in u for u in x.get("unmeasured", [])) for x in log)  # the report counts what it says
    assert re.search(rf"left a turn unmeasured .*: {turns} of {spec.frames}\.$", report, re.M)
    for image in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", report):  # every picture the report shows is there
        assert cv2.imread(str(tmp_path / image)) is not None, image
    assert "mesh_vs_gt.png" in report
    video = cv2.VideoCapture(str(tmp_path / "overlay.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == spec.frames
    video.release()
