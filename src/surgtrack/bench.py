"""Benchmark: run methods (surgtrack and its ablations) over a synthetic suite, evaluate, tabulate like the paper."""

from __future__ import annotations

import copy
import hashlib
import json
import multiprocessing
import resource
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from .baselines import BaselineTracker, FrameToFrameICPTracker, KinectFusionTracker, RansacOnlyTracker
from .config import TrackerConfig
from .io import open_sequence, sequence_digest, write_text_atomic
from .metrics import evaluate
from .pipeline import track_sequence
from .plots import plot_accuracy, plot_errors_over_time
from .synth import is_rendered, render_sequence, suite_specs
from .tracker import SurgTracker


def method_config(name: str, base: TrackerConfig | None = None) -> TrackerConfig:
    """The tracker configuration of a named method (the paper's Table 2 ablations are switches of one config): the
    method's switch on a copy of ``base`` (default: the defaults)."""
    cfg = copy.deepcopy(base) if base is not None else TrackerConfig()
    if name == "surgtrack":
        return cfg
    if name == "no-memory-pool":
        cfg.pool = replace(cfg.pool, enabled=False)
    elif name == "no-graph":
        cfg.graph = replace(cfg.graph, enabled=False)
    elif name == "no-occ-surf":
        cfg.sdf = replace(cfg.sdf, occ_surf=False)
    elif name in ("orb", "xfeat"):
        cfg.ransac = replace(cfg.ransac, features=name)
    else:
        raise ValueError(f"unknown SurgTracker variant {name!r}; choose from {', '.join(SURGTRACK_METHODS)}")
    return cfg


SURGTRACK_METHODS = ("surgtrack", "no-memory-pool", "no-graph", "no-occ-surf", "orb", "xfeat")
BASELINES: dict[str, type[BaselineTracker]] = {
    "kinectfusion": KinectFusionTracker, "icp": FrameToFrameICPTracker, "ransac-only": RansacOnlyTracker}
METHODS = SURGTRACK_METHODS + tuple(BASELINES)


def make_tracker(name: str, base: TrackerConfig | None = None) -> SurgTracker | BaselineTracker:
    """A fresh tracker for a named method: a SurgTracker variant (``method_config`` on ``base``) or a baseline
    (which has settings of its own)."""
    if name in BASELINES:
        return BASELINES[name]()
    return SurgTracker(method_config(name, base))


def run_bench(suite: str, methods: list[str], root: Path | str, short: bool = False, frames: int | None = None,
              first_mask_only: bool = False, log: Callable[[str], None] = print,
              config: TrackerConfig | None = None) -> dict:
    """Render the suite if needed, run every method on every sequence, evaluate; returns the bench.json dict.
    ``log`` gets a line per rendered and per tracked sequence (it runs in each method's process: a module-level
    function such as ``print``). ``config`` is the SurgTracker methods' base configuration (default: the
    defaults); bench.json records it."""
    root = Path(root)
    results: dict = {"suite": suite, "short": short, "frames": frames, "first_mask_only": first_mask_only,
                     "config": None if config is None else config.to_dict(), "methods": {}}
    specs = suite_specs(suite, short, frames)
    for name, spec in specs:
        path = root / "data" / name
        if not is_rendered(spec, path):
            log(f"rendering {name} ({spec.frames} frames, {spec.width}x{spec.height})")
            render_sequence(spec, path)
    results["data_sha256"] = {name: sequence_digest(root / "data" / name) for name, _ in specs}
    errors: dict[str, dict[str, list]] = {}
    first_seq: dict[str, dict] = {}
    names = [name for name, _ in specs]
    for method in methods:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
        # Each method runs in a child process of its own, so its peak memory is its own.
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork")) as pool:
            per_seq, errors[method], first_seq[method], peak = pool.submit(
                _run_method, method, names, root, first_mask_only, log, config).result()
        results["methods"][method] = {"sequences": per_seq, **_mean(per_seq), "peak_rss_mb": peak}
    results["plots"] = [p.name for p in (
        plot_accuracy({k: v["ADD"] for k, v in errors.items()}, root / "accuracy_add.png", "ADD"),
        plot_accuracy({k: v["ADD-S"] for k, v in errors.items()}, root / "accuracy_add_s.png", "ADD-S"),
        plot_errors_over_time(first_seq, root / f"errors_over_time_{specs[0][0]}.png", "ADD"))]
    write_text_atomic(root / "bench.json", json.dumps(results, indent=2))
    write_text_atomic(root / "bench.md", format_table(results))
    return results


def _run_method(method: str, names: list[str], root: Path, first_mask_only: bool, log: Callable[[str], None],
                config: TrackerConfig | None = None) -> tuple[dict, dict, dict, float]:
    """One method over every sequence: per-sequence figures, all per-frame errors, the first sequence's ADD errors
    and the process's peak memory (MB)."""
    per_seq, errors, first = {}, {"ADD": [], "ADD-S": []}, {}
    for name in names:
        seq = open_sequence(root / "data" / name)
        out = root / method / name
        t0 = time.perf_counter()
        tracker = make_tracker(method, config)
        summary = track_sequence(seq, out, tracker.cfg, first_mask_only, tracker=tracker)
        m = evaluate(out, seq)
        errors["ADD"] += list(m["errors"]["add"].values())
        errors["ADD-S"] += list(m["errors"]["add_s"].values())
        if name == names[0]:
            first = m["errors"]["add"]
        per_seq[name] = {"add_s_auc": m["add_s_auc"], "add_auc": m["add_auc"], "cd_cm": m["cd_cm"],
                         "add_s_auc_full": m["add_s_auc_full"], "add_auc_full": m["add_auc_full"],
                         "lost": summary.lost, "lost_because": summary.lost_because, "wrong": m["wrong"],
                         "unmeasured": dict(summary.unmeasured),
                         "frames": summary.frames, "fps": summary.fps,
                         "sdf_frames": summary.sdf_frames, "sdf_from": summary.sdf_from,
                         "stage_ms": summary.stage_ms, "seconds": time.perf_counter() - t0}
        log(f"{method:>15} {name:<18} ADD-S {m['add_s_auc']:6.2f}  ADD {m['add_auc']:6.2f}  "
            f"lost {summary.lost:3d}  L_SDF {summary.sdf_frames:3d}  {summary.fps:5.1f} fps")
    return per_seq, errors, first, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _mean(per_seq: dict) -> dict:
    def avg(key: str) -> float | None:
        vals = [v[key] for v in per_seq.values() if v[key] is not None]
        return float(np.mean(vals)) if vals else None

    frames = sum(v["frames"] for v in per_seq.values())
    seconds = sum(v["frames"] / v["fps"] for v in per_seq.values() if v["fps"] > 0)
    stages = {k: float(np.mean([v["stage_ms"].get(k, 0.0) for v in per_seq.values()]))
              for k in {k for v in per_seq.values() for k in v["stage_ms"]}}
    lost = sum(v["lost"] for v in per_seq.values())
    wrong = sum(v["wrong"] for v in per_seq.values())
    return {"add_s_auc": avg("add_s_auc"), "add_auc": avg("add_auc"), "cd_cm": avg("cd_cm"),
            "lost_pct": 100 * lost / frames if frames else None,
            "wrong_pct": 100 * wrong / (frames - lost) if frames > lost else None,
            "fps": frames / seconds if seconds else 0.0, "stage_ms": stages}


def suite_digest(digests: dict[str, str]) -> str:
    """One SHA-256 over the sequences' digests (`io.sequence_digest`), in name order: the suite's data at a glance."""
    return hashlib.sha256("".join(f"{k}:{v}\n" for k, v in sorted(digests.items())).encode()).hexdigest()


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def format_table(results: dict) -> str:
    """The paper's layout: one row a method (ADD-S AUC %, ADD AUC %, CD cm, frames/s), then per-sequence detail.
    Beside the paper's columns: the share of frames reported lost, and of the frames given a pose, the share more
    than 5 cm off in ADD-S (`metrics.WRONG_ERR`: a lost instrument not reported lost)."""
    lines = [f"## {results['suite']}" + (" (first-frame mask only)" if results["first_mask_only"] else ""), "",
             "| method | ADD-S AUC % | ADD AUC % | CD cm | lost % | wrong % | frames/s | peak MB | ms per stage |",
             "|---|---|---|---|---|---|---|---|---|"]
    for method, r in results["methods"].items():
        stages = ", ".join(f"{k} {v:.1f}" for k, v in sorted(r["stage_ms"].items()))
        peak = f"{r['peak_rss_mb']:.0f}" if r.get("peak_rss_mb") else "-"
        lines.append(f"| {method} | {_fmt(r['add_s_auc'])} | {_fmt(r['add_auc'])} | {_fmt(r['cd_cm'])} | "
                     f"{_fmt(r.get('lost_pct'))} | {_fmt(r.get('wrong_pct'))} | {r['fps']:.1f} | {peak} | {stages} |")
    lines += ["", "| sequence | " + " | ".join(f"{m} ADD-S / ADD" for m in results["methods"]) + " |",
              "|---|" + "---|" * len(results["methods"])]
    names = next(iter(results["methods"].values()))["sequences"].keys() if results["methods"] else []
    for name in names:
        cells = [f"{_fmt(r['sequences'][name]['add_s_auc'])} / {_fmt(r['sequences'][name]['add_auc'])}"
                 for r in results["methods"].values()]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if results.get("data_sha256"):
        lines += ["", f"Data: SHA-256 {suite_digest(results['data_sha256'])[:16]} over the sequences' digests "
                      "(bench.json `data_sha256`); figures compare only on the same data."]
    lines += ["", *[f"![{p}]({p})" for p in results.get("plots", [])]]
    return "\n".join(lines) + "\n"
