"""Command-line interface: thin wrappers over the library (one command a workflow, DESIGN.md section 1)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

from .igtl import (
    DEFAULT_COLOUR_DEVICE,
    DEFAULT_DEVICE,
    DEFAULT_REASON_DEVICE,
    DEFAULT_STATUS_DEVICE,
    DEFAULT_UNMEASURED_DEVICE,
)
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
    ctx: typer.Context,
    out: Annotated[Path, typer.Argument(help="output folder (one sequence, or the root of a suite)")],
    instrument: Annotated[str, typer.Option(help="procedural name, shared mesh stem or mesh file")] = "forceps",
    suite: Annotated[str | None, typer.Option(help="render a whole suite: instrument3d | ho3d")] = None,
    short: Annotated[bool, typer.Option("--short", help="suite: 40 frames at 320x240")] = False,
    frames: Annotated[int | None, typer.Option(
        help="number of frames (default 300; with --suite, each sequence cut to this many, as bench --frames)")] = None,
    size: Annotated[str, typer.Option(help="WIDTHxHEIGHT")] = "640x480",
    seed: Annotated[int, typer.Option(
        help="random seed (same seed, same files on one machine; bench prints the data's digest)")] = 0,
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

    if suite is not None:
        given = [name for name in ("instrument", "size", "seed", "occluders", "full_occlusion", "fast", "speed", "fps",
                                   "noise", "motion_blur", "background")
                 if getattr(ctx.get_parameter_source(name), "name", None) == "COMMANDLINE"]
        if given:
            fail(f"{', '.join('--' + g.replace('_', '-') for g in given)}: for one sequence; --suite renders the "
                 f"suite's own (--short and --frames apply to it)")
    else:
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
                paths = render_suite(suite, out, short=short, frames=frames, progress=on_frame)
            else:
                spec = SynthSpec(instrument=instrument, frames=300 if frames is None else frames, width=w, height=h,
                                 fps=fps, speed=speed, seed=seed, n_occluders=occluders, noise=noise,
                                 motion_blur=motion_blur,
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

    from .io import open_sequence, write_text_atomic
    from .metrics import WRONG_ERR, evaluate

    positive_depth_scale(depth_scale)
    result = evaluate(out, open_sequence(seq, depth_scale=depth_scale, obj_id=obj_id))
    write_text_atomic(out / "metrics.json", json.dumps(result, indent=1) + "\n")
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
    table.add_row(f"posed frames over {100 * WRONG_ERR:g} cm off (ADD-S)", str(result["wrong"]))
    Console().print(table)
    if plot:
        from .plots import plot_evaluation

        for p in plot_evaluation(result, out, method=out.name or "result"):
            typer.echo(f"wrote {p}")
    typer.echo(f"wrote {out / 'metrics.json'}")


def positive_depth_scale(depth_scale: float) -> None:
    """Stop on a --depth-scale of 0 or less (every depth would read as invalid or behind the camera)."""
    if not depth_scale > 0:
        fail(f"--depth-scale must be positive, got {depth_scale}")


def load_config(path: Path | None, **overrides: object):
    """Tracker config from an optional JSON file (TrackerConfig.to_dict layout), then the command-line switches
    that were given (None: not given)."""
    import json

    from .config import TrackerConfig
    from .features import KINDS

    cfg = TrackerConfig()
    if path is not None:
        try:
            cfg = TrackerConfig.from_dict(json.loads(path.read_text()))
        except (OSError, ValueError, TypeError) as e:
            fail(f"{path}: bad config ({e})")
    for key, value in overrides.items():
        if value is None:  # a switch not given: the file's (or the default) value stands
            continue
        section, name = key.split(".")
        setattr(getattr(cfg, section), name, value)
    if cfg.ransac.features not in KINDS:
        given = "--features" if overrides.get("ransac.features") is not None else f"{path}: ransac.features"
        fail(f"{given}: unknown feature type {cfg.ransac.features!r} ({', '.join(KINDS)})")
    return cfg


@app.command()
def track(
    seq: Annotated[Path, typer.Argument(help="sequence folder (rgb/ depth/ masks/ cam_K.txt, or a BOP scene)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="output folder")],
    first_mask_only: Annotated[bool, typer.Option(help="use only the first frame's mask, make the rest")] = False,
    features: Annotated[str | None, typer.Option(help="sift | orb | xfeat  [default: sift, or --config's]")] = None,
    no_memory_pool: Annotated[bool, typer.Option("--no-memory-pool", help="ablation: adjacent frames only")] = False,
    no_graph: Annotated[bool, typer.Option("--no-graph", help="ablation: RANSAC + Kabsch only")] = False,
    no_occ_surf: Annotated[bool, typer.Option("--no-occ-surf", help="ablation: SDF without L_occ and L_surf")] = False,
    depth_scale: Annotated[float, typer.Option(help="metres per depth unit")] = 0.001,
    config: Annotated[Path | None, typer.Option(help="JSON config (see OUT/config.json of any run)")] = None,
    video: Annotated[Path | None, typer.Option(help="also write an overlay video (model outline, axes, lost frames)")]
    = None,
    model: Annotated[Path | None, typer.Option(help="registered instrument model (NAME.stm from surgtrack register)")]
    = None,
) -> None:
    """Track an instrument through a recorded RGB-D video: a pose per frame and a mesh, in OUT."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from .io import open_sequence
    from .pipeline import track_sequence
    from .tracker import SurgTracker

    positive_depth_scale(depth_scale)
    cfg = load_config(config, **{"ransac.features": features, "pool.enabled": False if no_memory_pool else None,
                                 "graph.enabled": False if no_graph else None,
                                 "sdf.occ_surf": False if no_occ_surf else None})
    sequence = open_sequence(seq, depth_scale=depth_scale)
    tracker = SurgTracker(cfg, model=_load_model(model, cfg) if model is not None else None)
    overlay = _OverlayWriter(video, tracker) if video is not None else None
    columns = (TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
               TimeRemainingColumn())

    def on_frame(frame, result) -> None:
        progress.update(task, completed=frame.index + 1, status=result.status)
        if overlay is not None:
            overlay.write(frame, result)

    try:
        with Progress(*columns, transient=True) as progress:
            task = progress.add_task("track", total=len(sequence), status="")
            summary = track_sequence(sequence, out, cfg, first_mask_only, on_frame=on_frame, tracker=tracker)
    finally:
        if overlay is not None:
            overlay.close()
    typer.echo(f"{summary.line()} -> {out}")
    if video is not None:
        typer.echo(f"wrote {video}")


def _load_model(path: Path, cfg):
    """A model file for `track --model` and `live --model`, checked against the tracker config (one-line errors)."""
    from .model import load_model

    instrument_model = load_model(path)
    try:
        instrument_model.check_compatible(cfg)
    except ValueError as e:
        fail(f"{path}: {e}; use --features {instrument_model.features}")
    return instrument_model


@app.command()
def register(
    seq: Annotated[Path, typer.Argument(help="scan video of the instrument (sequence folder or BOP scene)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="model file to write (NAME.stm)")],
    first_mask_only: Annotated[bool, typer.Option(help="use only the first frame's mask, make the rest")] = False,
    depth_scale: Annotated[float, typer.Option(help="metres per depth unit")] = 0.001,
    config: Annotated[Path | None, typer.Option(help="JSON config (see OUT/config.json of any run)")] = None,
    results: Annotated[Path | None, typer.Option(help="folder for the scan's poses and mesh [default: NAME_register "
                                                      "beside the model]")] = None,
) -> None:
    """Build an instrument model (SDF, mesh, keyframes with features) from a scan video, for `track --model`."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from .io import open_sequence
    from .model import InstrumentModel, save_model
    from .pipeline import track_sequence
    from .tracker import SurgTracker

    positive_depth_scale(depth_scale)
    if out.is_dir():
        fail(f"{out}: is a folder; --out names the model file to write (NAME.stm)")
    cfg = load_config(config)
    sequence = open_sequence(seq, depth_scale=depth_scale)
    results = results if results is not None else out.with_name(f"{out.stem}_register")
    tracker = SurgTracker(cfg)
    columns = (TextColumn("scanning"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[status]}"),
               TimeRemainingColumn())
    with Progress(*columns, transient=True) as progress:
        task = progress.add_task("register", total=len(sequence), status="")
        summary = track_sequence(sequence, results, cfg, first_mask_only, tracker=tracker,
                                 on_frame=lambda f, r: progress.update(task, completed=f.index + 1, status=r.status))
    instrument_model = InstrumentModel.from_tracker(
        tracker, {"source": str(seq.resolve()), "frames": summary.frames, "lost": summary.lost})
    try:
        save_model(instrument_model, out)
    except OSError as e:
        fail(f"{out}: cannot write the model ({e.strerror or e})")
    sdf = instrument_model.sdf
    field = "no SDF" if sdf is None else f"SDF {'x'.join(map(str, sdf.grid.shape))} at {sdf.grid.voxel * 1e3:g} mm"
    faces = 0 if instrument_model.mesh is None else len(instrument_model.mesh.faces)
    typer.echo(f"{summary.frames} frames, {summary.lost} lost -> scan poses and mesh in {results}")
    typer.echo(f"model: {len(instrument_model.keyframes)} keyframes, {field}, mesh {faces} faces, "
               f"{out.stat().st_size / 1e6:.1f} MB -> {out}")


class _OverlayWriter:
    """Overlay video of tracked frames (the tracker's keyframe points outlined at each pose), opened at the first
    frame's size."""

    def __init__(self, path: Path, tracker, fps: float = 15.0):
        self.path, self.tracker, self.fps = path, tracker, fps
        self._video = None

    def write(self, frame, result) -> None:
        from .overlay import OverlayVideo, draw_result

        if self._video is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            try:
                self._video = OverlayVideo(self.path, (frame.rgb.shape[1], frame.rgb.shape[0]), self.fps)
            except OSError as e:
                fail(str(e))
        self._video.write(draw_result(frame, result, self.tracker.model_points))

    def close(self) -> None:
        if self._video is not None:
            self._video.close()


@app.command()
def live(
    file: Annotated[Path | None, typer.Option("--file", help="play a RealSense recording instead of reading a "
                                                             "camera")] = None,
    mask: Annotated[Path | None, typer.Option(help="first frame's instrument mask (PNG, >0 = instrument)")] = None,
    box: Annotated[str | None, typer.Option(help="x0,y0,x1,y1 box around the instrument in the first frame: the mask "
                                                 "is the depth-continuous surface of the nearest depth cluster in it")]
    = None,
    igtl_port: Annotated[int, typer.Option(help="OpenIGTLink server port (0: any free port)")] = 18944,
    no_igtl: Annotated[bool, typer.Option("--no-igtl", help="do not stream poses over OpenIGTLink")] = False,
    igtl_interface: Annotated[str | None, typer.Option(help="network interface to listen on (e.g. eth0; default: "
                                                           "127.0.0.1 only)")] = None,
    device_name: Annotated[str, typer.Option(help="OpenIGTLink device name of the TRANSFORM messages")]
    = DEFAULT_DEVICE,
    status_device: Annotated[str, typer.Option(help="OpenIGTLink device name of the STRING status messages")]
    = DEFAULT_STATUS_DEVICE,
    reason_device: Annotated[str, typer.Option(help="OpenIGTLink device name of the STRING messages saying why a "
                                                    "frame is lost (empty when tracked)")]
    = DEFAULT_REASON_DEVICE,
    unmeasured_device: Annotated[str, typer.Option(help="OpenIGTLink device name of the STRING messages saying what "
                                                        "the frame's data left free (turn, slide; empty: nothing)")]
    = DEFAULT_UNMEASURED_DEVICE,
    colour_device: Annotated[str, typer.Option(help="OpenIGTLink device name of the STRING messages saying how "
                                                    "instrument-like the frame's made mask looks (empty: none)")]
    = DEFAULT_COLOUR_DEVICE,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="also write ob_in_cam/ and track.jsonl here")]
    = None,
    video: Annotated[Path | None, typer.Option(help="write an overlay video")] = None,
    max_frames: Annotated[int | None, typer.Option(help="stop after this many frames")] = None,
    size: Annotated[str, typer.Option(help="camera stream WIDTHxHEIGHT")] = "640x480",
    fps: Annotated[int, typer.Option(help="camera frame rate")] = 30,
    config: Annotated[Path | None, typer.Option(help="JSON config (see OUT/config.json of any run)")] = None,
    model: Annotated[Path | None, typer.Option(help="registered instrument model (NAME.stm from surgtrack register): "
                                                    "poses in its object frame, its SDF from the first frame")]
    = None,
) -> None:
    """Track an instrument live from a RealSense camera (or a recording) and stream its pose over OpenIGTLink."""
    import time

    from .io import ResultWriter, check_first_mask, read_mask
    from .realsense import RealSenseError, RealSenseSource, box_mask, parse_box

    if (mask is None) == (box is None):
        fail("give the first frame's instrument with --mask FILE or with --box x0,y0,x1,y1 (one of them)")
    try:
        box_xyxy = parse_box(box) if box is not None else None
    except ValueError as e:
        fail(f"--box: {e}")
    try:
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError:
        fail(f"--size expects WIDTHxHEIGHT, got {size!r}")
    if max_frames is not None and max_frames < 1:
        fail(f"--max-frames must be at least 1, got {max_frames}")
    first_mask = read_mask(mask) if mask is not None else None
    cfg = load_config(config)
    instrument_model = _load_model(model, cfg) if model is not None else None
    try:
        source = RealSenseSource(file, width, height, fps)
    except RealSenseError as e:
        fail(str(e))
    from .pipeline import RunSummary, frame_record
    from .tracker import SurgTracker

    streamer = writer = tracker = None
    overlay: _OverlayWriter | None = None
    summary = RunSummary()
    t0 = time.perf_counter()
    try:
        if not no_igtl:
            from .igtl import PoseStreamer

            try:
                streamer = PoseStreamer(igtl_port, device_name, status_device, interface=igtl_interface,
                                        reason_device=reason_device, unmeasured_device=unmeasured_device,
                                        colour_device=colour_device)
            except (OSError, ValueError) as e:
                fail(f"OpenIGTLink server on port {igtl_port}: {e}")
            typer.echo(f"streaming {device_name} (mm), {status_device}, {reason_device}, {unmeasured_device} and "
                       f"{colour_device} over OpenIGTLink on port {streamer.port}")
        if out is not None:
            writer = ResultWriter(out, cfg.to_dict())
        tracker = SurgTracker(cfg, model=instrument_model)
        if video is not None:
            overlay = _OverlayWriter(video, tracker, source.fps)
        for n, frame in enumerate(source):
            if n == 0:
                if first_mask is None:
                    try:
                        first_mask = box_mask(frame.depth, box_xyxy)
                    except ValueError as e:
                        fail(f"--box: {e}")
                if first_mask.shape != frame.depth.shape:
                    fail(f"{mask}: mask size {first_mask.shape[1]}x{first_mask.shape[0]} != frame size "
                         f"{frame.depth.shape[1]}x{frame.depth.shape[0]}")
                if mask is not None:
                    try:
                        check_first_mask(mask, first_mask)
                    except SequenceError as e:
                        fail(str(e))
                try:
                    result = tracker.first_result(tracker.register(frame, first_mask))
                except ValueError as e:
                    fail(str(e))
            else:
                result = tracker.track(frame)
            if streamer is not None:
                streamer.send(result)
            if writer is not None:
                writer.write(frame.id, result.pose, frame_record(result))
            if overlay is not None:
                overlay.write(frame, result)
            summary.add(n, result)
            if max_frames is not None and summary.frames >= max_frames:
                break
    except KeyboardInterrupt:
        typer.echo("stopped")
    except RealSenseError as e:
        fail(str(e))
    finally:
        source.close()
        fitter = getattr(tracker, "fitter", None)
        if fitter is not None:
            fitter.close()
        if streamer is not None:
            streamer.close()
        summary.seconds = time.perf_counter() - t0
        if writer is not None:
            writer.close()
            if summary.frames:
                summary.write(out)
        if overlay is not None:
            overlay.close()
    if summary.frames == 0:
        fail(f"{file or 'camera'}: no frames")
    typer.echo(summary.line() + (f" -> {out}" if out is not None else ""))


@app.command()
def bench(
    suite: Annotated[str, typer.Option(help="instrument3d | ho3d")] = "instrument3d",
    methods: Annotated[str, typer.Option(help="comma-separated: surgtrack, no-memory-pool, no-graph, no-occ-surf, "
                                              "orb, xfeat")] = "surgtrack,no-memory-pool,no-graph",
    out: Annotated[Path, typer.Option("--out", "-o", help="working folder")] = Path("runs/bench"),
    short: Annotated[bool, typer.Option(help="40-frame 320x240 variants")] = False,
    frames: Annotated[int | None, typer.Option(help="cut every sequence to this many frames")] = None,
    first_mask_only: Annotated[bool, typer.Option(help="give the trackers the first mask only")] = False,
    config: Annotated[Path | None, typer.Option(
        help="JSON config for the surgtrack methods, the ablations switched on top (see OUT/config.json of any run); "
             '{"sdf": {"background": false}} makes a run repeatable')] = None,
) -> None:
    """Run methods over a synthetic suite, evaluate, and print the paper-style table (writes bench.json/.md)."""
    from .bench import METHODS, format_table, run_bench
    from .io import make_folder

    names = [m.strip() for m in methods.split(",") if m.strip()]
    for m in names:
        if m not in METHODS:
            fail(f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    if frames is not None and frames < 1:
        fail(f"--frames must be at least 1, got {frames}")
    cfg = load_config(config) if config is not None else None
    results = run_bench(suite, names, make_folder(out), short, frames, first_mask_only, log=typer.echo, config=cfg)
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
    from .io import make_folder

    make_folder(out)
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
