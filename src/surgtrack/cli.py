"""Command-line interface: thin wrappers over the library (one command a workflow, DESIGN.md section 1)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from .io import SequenceError

app = typer.Typer(help="CAD-free 6-DoF tracking and reconstruction of surgical instruments from RGB-D video.",
                  no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)


def fail(message: str) -> None:
    """Print a one-line error and exit non-zero."""
    typer.secho(f"surgtrack: error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2)


def main() -> None:
    try:
        app()
    except SequenceError as e:
        print(f"surgtrack: error: {e}", file=sys.stderr)
        sys.exit(2)


_ = (Path, Annotated)  # used by the commands below


@app.command()
def synth(
    out: Annotated[Path, typer.Argument(help="output folder (one sequence, or the root of a suite)")],
    instrument: Annotated[str, typer.Option(help="procedural name, shared mesh stem or mesh file")] = "forceps",
    suite: Annotated[str | None, typer.Option(help="render a whole suite: instrument3d | ho3d")] = None,
    short: Annotated[bool, typer.Option("--short", help="suite: 40 frames at 320x240")] = False,
    frames: Annotated[int, typer.Option(help="number of frames")] = 300,
    size: Annotated[str, typer.Option(help="WIDTHxHEIGHT")] = "640x480",
    seed: Annotated[int, typer.Option(help="random seed (same seed, same files)")] = 0,
    occluders: Annotated[int, typer.Option(help="moving hands in front of the instrument (0-3)")] = 1,
    full_occlusion: Annotated[list[str] | None, typer.Option(help="START:LENGTH frames fully covered (repeatable)")]
    = None,
    fast: Annotated[list[str] | None, typer.Option(help="START:LENGTH frames of fast motion (repeatable)")] = None,
    speed: Annotated[float, typer.Option(help="motion speed multiplier")] = 1.0,
    fps: Annotated[float, typer.Option(help="frame rate")] = 30.0,
    noise: Annotated[bool, typer.Option("--noise/--no-noise", help="RealSense sensor model")] = True,
    motion_blur: Annotated[bool, typer.Option("--motion-blur/--no-motion-blur")] = True,
    background: Annotated[str, typer.Option(help="auto | drape_green | drape_blue | steel_table | wood | foam_grey")]
    = "auto",
) -> None:
    """Render a synthetic RealSense-like RGB-D sequence of an instrument with ground truth (or a whole suite)."""
    import time

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TaskID, TextColumn, TimeRemainingColumn

    from .synth import SynthSpec, render_sequence, render_suite

    def spans(values: list[str] | None, name: str) -> tuple[tuple[int, int], ...]:
        out_spans = []
        for v in values or []:
            try:
                a, b = (int(x) for x in v.split(":"))
            except ValueError:
                fail(f"{name} expects START:LENGTH, got {v!r}")
            out_spans.append((a, b))
        return tuple(out_spans)

    if suite is None:
        try:
            w, h = (int(x) for x in size.lower().split("x"))
        except ValueError:
            fail(f"--size expects WIDTHxHEIGHT, got {size!r}")
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    start = time.perf_counter()
    with Progress(*columns, transient=True) as progress:
        tasks: dict[str, TaskID] = {}

        def on_frame(name: str, i: int, n: int) -> None:
            if name not in tasks:
                tasks[name] = progress.add_task(name, total=n)
            progress.update(tasks[name], completed=i)

        try:
            if suite is not None:
                paths = render_suite(suite, out, short=short, progress=on_frame)
            else:
                spec = SynthSpec(instrument=instrument, frames=frames, width=w, height=h, fps=fps, speed=speed,
                                 seed=seed, n_occluders=occluders, noise=noise, motion_blur=motion_blur,
                                 full_occlusions=spans(full_occlusion, "--full-occlusion"),
                                 fast_segments=spans(fast, "--fast"), background=background)
                paths = [render_sequence(spec, out, lambda i, n: on_frame(out.name or "synth", i, n))]
        except (ValueError, FileNotFoundError, FileExistsError) as e:
            fail(str(e))
        n_frames = sum(int(t.total or 0) for t in progress.tasks)
    elapsed = time.perf_counter() - start
    timing = f"{1000 * elapsed / n_frames:.0f} ms/frame" if n_frames else "nothing to render"
    typer.echo(f"{len(paths)} sequence(s) in {out}, {len(tasks)} rendered, {elapsed:.1f} s ({timing})")


@app.command("eval")
def eval_cmd(
    out: Annotated[Path, typer.Argument(help="Result folder (ob_in_cam/, optional mesh.ply).")],
    seq: Annotated[Path, typer.Argument(help="Sequence folder with ground truth (DESIGN layout, BOP or APC scene).")],
    depth_scale: Annotated[float, typer.Option(help="Metres per depth unit of the DESIGN layout.")] = 0.001,
    plot: Annotated[bool, typer.Option("--plot", help="Write accuracy curves and errors over time as PNGs.")] = False,
    obj_id: Annotated[int | None, typer.Option(help="Object id to score in a BOP scene.")] = None,
) -> None:
    """Score a result against ground truth (ADD, ADD-S AUC, Chamfer distance) and write OUT/metrics.json."""
    import json

    from rich.console import Console
    from rich.table import Table

    from .io import open_sequence
    from .metrics import evaluate

    if not depth_scale > 0:
        fail(f"--depth-scale must be positive, got {depth_scale}")
    result = evaluate(out, open_sequence(seq, depth_scale=depth_scale, obj_id=obj_id))
    (out / "metrics.json").write_text(json.dumps(result, indent=1) + "\n")
    table = Table(title=f"{out.name} vs {seq.name}")
    table.add_column("metric")
    table.add_column("value", justify="right")

    def fmt(v: float | None, unit: str) -> str:
        return "-" if v is None else f"{v:.2f}{unit}"

    for key, label, unit in [("add_s_auc", "ADD-S AUC", " %"), ("add_auc", "ADD AUC", " %"),
                             ("add_s_auc_full", "ADD-S AUC, whole model", " %"),
                             ("add_auc_full", "ADD AUC, whole model", " %"), ("cd_cm", "Chamfer distance", " cm")]:
        table.add_row(label, fmt(result[key], unit))
    table.add_row("frames scored / missing", f"{result['frames']} / {result['missing']}")
    Console().print(table)
    if plot:
        from .plots import plot_evaluation

        for p in plot_evaluation(result, out, method=out.name or "result"):
            typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out / 'metrics.json'}")


def load_config(path: Path | None, **overrides: object):
    """Tracker config from an optional JSON file (TrackerConfig.to_dict layout), then command-line switches."""
    import json

    from .config import TrackerConfig

    cfg = TrackerConfig()
    if path is not None:
        try:
            cfg = TrackerConfig.from_dict(json.loads(path.read_text()))
        except (OSError, ValueError, TypeError) as e:
            fail(f"{path}: bad config ({e})")
    for key, value in overrides.items():
        section, name = key.split(".")
        setattr(getattr(cfg, section), name, value)
    return cfg


@app.command()
def track(
    seq: Annotated[Path, typer.Argument(help="sequence folder (rgb/ depth/ masks/ cam_K.txt, or a BOP scene)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder")],
    first_mask_only: Annotated[bool, typer.Option(help="use only the first frame's mask, make the rest")] = False,
    features: Annotated[str, typer.Option(help="sift | orb | xfeat")] = "sift",
    no_memory_pool: Annotated[bool, typer.Option("--no-memory-pool", help="ablation: adjacent frames only")] = False,
    no_graph: Annotated[bool, typer.Option("--no-graph", help="ablation: RANSAC + Kabsch only")] = False,
    depth_scale: Annotated[float, typer.Option(help="metres per depth unit")] = 0.001,
    config: Annotated[Path | None, typer.Option(help="JSON config (see OUT/config.json of any run)")] = None,
) -> None:
    """Track an instrument through a recorded RGB-D video: a pose per frame and a mesh, in OUT."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from .io import open_sequence
    from .pipeline import track_sequence

    cfg = load_config(config, **{"ransac.features": features, "pool.enabled": not no_memory_pool,
                                 "graph.enabled": not no_graph})
    sequence = open_sequence(seq, depth_scale=depth_scale)
    columns = (TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
               TimeRemainingColumn())
    with Progress(*columns, transient=True) as progress:
        task = progress.add_task("track", total=len(sequence), status="")
        summary = track_sequence(sequence, out, cfg, first_mask_only,
                                 on_frame=lambda f, r: progress.update(task, completed=f.index + 1, status=r.status))
    stages = ", ".join(f"{k} {v:.1f}" for k, v in summary.stage_ms.items())
    typer.echo(f"{summary.frames} frames, {summary.lost} lost, {summary.fps:.1f} frames/s ({stages} ms) -> {out}")


@app.command()
def bench(
    suite: Annotated[str, typer.Option(help="instrument3d | ho3d")] = "instrument3d",
    methods: Annotated[str, typer.Option(help="comma-separated: surgtrack, no-memory-pool, no-graph, no-occ-surf, "
                                              "orb, xfeat")] = "surgtrack,no-memory-pool,no-graph",
    out: Annotated[Path, typer.Option("--out", "-o", help="working folder")] = Path("runs/bench"),
    short: Annotated[bool, typer.Option(help="40-frame 320x240 variants")] = False,
    frames: Annotated[int | None, typer.Option(help="cut every sequence to this many frames")] = None,
    first_mask_only: Annotated[bool, typer.Option(help="give the trackers the first mask only")] = False,
) -> None:
    """Run methods over a synthetic suite, evaluate, and print the paper-style table (writes bench.json/.md)."""
    from .bench import METHODS, format_table, run_bench

    names = [m.strip() for m in methods.split(",") if m.strip()]
    for m in names:
        if m not in METHODS:
            fail(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    results = run_bench(suite, names, out, short, frames, first_mask_only, log=typer.echo)
    typer.echo(format_table(results))


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="report folder")] = Path("demo_out"),
    frames: Annotated[int, typer.Option(help="length of the synthetic video")] = 120,
    per_frame_masks: Annotated[bool, typer.Option(help="give the tracker every frame's mask")] = False,
) -> None:
    """Synthesise an instrument video, track it from the first-frame mask, evaluate, write OUT/report.md."""
    from dataclasses import replace

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

    from .demo import DEMO_SPEC, run_demo

    with Progress(TextColumn("{task.description:>8}"), BarColumn(), MofNCompleteColumn()) as progress:
        tasks: dict[str, int] = {}

        def update(stage: str, i: int, n: int) -> None:
            if stage not in tasks:
                tasks[stage] = progress.add_task(stage, total=n)
            progress.update(tasks[stage], completed=i)

        result = run_demo(out, replace(DEMO_SPEC, frames=frames), not per_frame_masks, update)
    m, s = result["metrics"], result["summary"]
    typer.echo(f"ADD-S AUC {m['add_s_auc']:.2f} %, ADD AUC {m['add_auc']:.2f} %, lost {s['lost']}/{s['frames']}, "
               f"{s['fps']:.1f} frames/s -> {result['report']}")
