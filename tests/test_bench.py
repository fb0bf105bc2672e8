"""Benchmark plumbing: method switches, shortened suite sequences, the paper-style table."""

from __future__ import annotations

import json

import pytest
from helpers import assert_one_line_error, surgtrack_here

from surgtrack.bench import _mean, format_table, method_config, suite_digest
from surgtrack.config import GraphConfig, PreprocessConfig, TrackerConfig
from surgtrack.synth import SynthSpec, shorten
from surgtrack.tracker import SurgTracker


def test_ablations_switch_one_component_each():
    assert method_config("surgtrack").pool.enabled and method_config("surgtrack").graph.enabled
    assert not method_config("no-memory-pool").pool.enabled
    assert not method_config("no-graph").graph.enabled
    assert not method_config("no-occ-surf").sdf.occ_surf
    assert method_config("orb").ransac.features == "orb"
    with pytest.raises(ValueError, match="unknown"):
        method_config("bundlesdf")


def test_ablations_switch_on_top_of_a_given_config():
    base = TrackerConfig()
    base.sdf.background = False
    base.graph.w_m = 3.0
    cfg = method_config("no-occ-surf", base)
    assert not cfg.sdf.occ_surf and not cfg.sdf.background and cfg.graph.w_m == 3.0
    assert base.sdf.occ_surf  # the given config is left as it was
    assert method_config("surgtrack", base).to_dict() == base.to_dict()


def test_bench_config_errors_are_one_line(tmp_path):
    bad = tmp_path / "cfg.json"
    bad.write_text('{"graph": {"no_such_weight": 1}}')
    assert_one_line_error(surgtrack_here("bench", "--config", bad, "--out", tmp_path / "b"), "cfg.json", "bad config")
    assert not (tmp_path / "b").exists()  # nothing rendered or run


@pytest.mark.parametrize(("text", "problem"), [
    ('{"graph": {"w_mm": 1}}', "unknown config key 'graph.w_mm'"),
    ('{"graph": {"w_m": "ten"}}', "graph.w_m must be float, got 'ten'"),
    ('{"sdf": {"enabled": 1}}', "sdf.enabled must be bool, got 1"),
    ('{"seed": 1.5}', "seed must be int, got 1.5"),
    ('{"preprocess": {"predicted_mask_margin": -3}}', "preprocess.predicted_mask_margin must be at least 0, got -3"),
    ('{"graph": {"huber_delta": 0}}', "graph.huber_delta must be above 0, got 0"),  # before: a LinAlgError
    ('{"sdf": {"refit_every": 0}}', "sdf.refit_every must be above 0, got 0"),  # before: a ZeroDivisionError
    ('{"preprocess": {"min_depth": 0.5, "max_depth": 0.3}}',
     "preprocess.max_depth \\(0.3\\) must be above preprocess.min_depth \\(0.5\\)"),
    ('{"graph": 3}', "graph must be a JSON object"),
    ("[1]", "the config must be a JSON object"),
])
def test_a_config_setting_of_the_wrong_name_or_type_is_named(text: str, problem: str):
    with pytest.raises(ValueError, match=problem.replace(".", r"\.")):
        TrackerConfig.from_dict(json.loads(text))


def test_a_config_built_in_code_is_checked_when_a_tracker_takes_it():
    with pytest.raises(ValueError, match=r"graph\.huber_delta must be above 0, got 0"):
        SurgTracker(TrackerConfig(graph=GraphConfig(huber_delta=0)))
    with pytest.raises(ValueError, match=r"preprocess\.predicted_mask_margin must be int, got 4\.0"):
        SurgTracker(TrackerConfig(preprocess=PreprocessConfig(predicted_mask_margin=4.0)))
    SurgTracker(TrackerConfig(graph=GraphConfig(w_m=0)))  # 0 turns a weight off


def test_a_config_reads_back_as_written_and_keeps_the_defaults_it_leaves_out():
    cfg = TrackerConfig.from_dict({"seed": 2, "graph": {"w_m": 3}, "sdf": {"enabled": False},
                                   "failure": {"relocalise_min_ncc": -1}})  # -1: the appearance check off
    assert (cfg.seed, cfg.graph.w_m, cfg.sdf.enabled, cfg.pool.K) == (2, 3, False, TrackerConfig().pool.K)
    assert TrackerConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_shorten_scales_occlusion_and_fast_stretches():
    spec = SynthSpec(frames=300, full_occlusions=((180, 20),), fast_segments=((60, 40),))
    short = shorten(spec, 100)
    assert short.frames == 100
    assert short.full_occlusions == ((60, 7),)
    assert short.fast_segments == ((20, 13),)


def test_table_has_a_row_per_method_and_sequence():
    seq = {"add_s_auc": 95.0, "add_auc": 90.0, "cd_cm": 0.4}
    results = {"suite": "instrument3d", "first_mask_only": False, "plots": ["a.png"],
               "methods": {m: {"add_s_auc": 95.0, "add_auc": 90.0, "cd_cm": None, "fps": 12.0, "peak_rss_mb": 500.0,
                               "stage_ms": {"graph": 20.0}, "sequences": {"s1": seq, "s2": seq}}
                           for m in ("surgtrack", "icp")}}
    table = format_table(results)
    assert "| surgtrack | 95.00 | 90.00 | - | - | - | 12.0 | 500 | graph 20.0 |" in table  # a bench.json of before
    assert "| s2 | 95.00 / 90.00 | 95.00 / 90.00 |" in table
    assert "![a.png](a.png)" in table
    assert "SHA-256" not in table  # a bench.json of before: no data digests
    with_data = format_table({**results, "data_sha256": {"s2": "b" * 64, "s1": "a" * 64}})
    assert f"Data: SHA-256 {suite_digest({'s1': 'a' * 64, 's2': 'b' * 64})[:16]} " in with_data
    assert suite_digest({"s1": "a" * 64, "s2": "b" * 64}) != suite_digest({"s1": "a" * 64, "s2": "c" * 64})


def test_table_reports_lost_frames_apart_from_frames_given_a_wrong_pose():
    """lost % is over every frame; wrong % over the frames given a pose, so an honest loss does not count as
    wrong."""
    def seq(lost: int, wrong: int) -> dict:
        return {"add_s_auc": 80.0, "add_auc": 70.0, "cd_cm": 0.5, "lost": lost, "wrong": wrong, "frames": 100,
                "fps": 10.0, "stage_ms": {"graph": 20.0}}

    mean = _mean({"s1": seq(lost=20, wrong=0), "s2": seq(lost=0, wrong=36)})
    assert mean["lost_pct"] == pytest.approx(10.0) and mean["wrong_pct"] == pytest.approx(20.0)
    table = format_table({"suite": "instrument3d", "first_mask_only": True,
                          "methods": {"surgtrack": {**mean, "sequences": {}}}})
    assert "| surgtrack | 80.00 | 70.00 | 0.50 | 10.00 | 20.00 | 10.0 | - | graph 20.0 |" in table
