"""Named suites of synthetic sequences: `instrument3d` (the paper's instrument dataset) and `ho3d` (YCB objects).

Sequences on the shared real meshes are listed only when the mesh folder is found (see instruments.meshes_dir);
the procedural ones always are.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

from .instruments import needs_mesh_file, resolve_mesh
from .render import is_rendered, render_sequence
from .spec import SynthSpec

SHORT_FRAMES, SHORT_SIZE = 40, (320, 240)

# name, instrument, seed, occluders, full occlusions, fast segments, speed (full-length frame numbers, of 300)
_INSTRUMENT3D: list[tuple[str, str, int, int, tuple, tuple, float]] = [
    ("bronchoscope_1", "bronchoscope", 101, 1, (), (), 1.0),
    ("bronchoscope_2", "bronchoscope", 102, 2, (), ((150, 40),), 1.0),
    ("endoscope_1", "rigid_endoscope", 103, 1, (), (), 1.0),
    ("endoscope_2", "rigid_endoscope", 104, 2, ((180, 20),), (), 1.0),
    ("endoscope_dvrk", "dvrk_endoscope", 105, 1, (), ((90, 30),), 1.0),
    ("thoracoscope_1", "thoracoscope", 106, 1, (), (), 1.0),
    ("thoracoscope_2", "thoracoscope", 107, 2, (), ((200, 40),), 1.2),
    ("thoracoscope_si", "si_endoscope", 108, 1, (), (), 1.0),
    ("ultrasound_1", "ultrasound_probe", 109, 1, (), (), 1.0),
    ("ultrasound_2", "ultrasound_probe", 110, 3, ((120, 25),), (), 1.0),
    ("forceps_1", "forceps", 111, 1, (), (), 1.0),
    ("forceps_2", "forceps", 112, 2, ((220, 20),), ((60, 40),), 1.0),
    ("forceps_dvrk", "dvrk_psm_instrument", 113, 2, (), (), 1.0),
]

_HO3D: list[tuple[str, str, int, int, tuple, tuple, float]] = [
    ("drill_1", "ycb_power_drill", 201, 1, (), (), 1.0),
    ("drill_2", "ycb_power_drill", 202, 2, (), ((150, 40),), 1.0),
    ("mustard_1", "ycb_mustard_bottle", 203, 1, (), (), 1.0),
    ("mustard_2", "ycb_mustard_bottle", 204, 2, (), (), 1.2),
]

SUITES = {"instrument3d": _INSTRUMENT3D, "ho3d": _HO3D}


def shorten(spec: SynthSpec, frames: int) -> SynthSpec:
    """The same sequence cut to ``frames`` frames, its occlusion and fast stretches scaled to fit."""
    if frames < 1:
        raise ValueError(f"cannot cut a sequence to {frames} frames")

    def scale(segments: tuple) -> tuple:
        return tuple((round(s * frames / spec.frames), max(1, round(n * frames / spec.frames))) for s, n in segments)

    return replace(spec, frames=frames, full_occlusions=scale(spec.full_occlusions),
                   fast_segments=scale(spec.fast_segments))


def suite_specs(name: str, short: bool = False, frames: int | None = None) -> list[tuple[str, SynthSpec]]:
    """(sequence name, spec) pairs of a suite; `short` gives 40 frames at 320x240 for tests, ``frames`` cuts every
    sequence to that many (`shorten`)."""
    if name not in SUITES:
        raise ValueError(f"unknown suite {name!r}; choose one of {', '.join(SUITES)}")
    out = []
    missing = []
    for seq, inst, seed, occ, full, fast, speed in SUITES[name]:
        if needs_mesh_file(inst) and resolve_mesh(inst) is None:
            missing.append(seq)
            continue
        spec = SynthSpec(instrument=inst, seed=seed, n_occluders=occ, full_occlusions=full, fast_segments=fast,
                         speed=speed)
        if short:
            spec = replace(shorten(spec, SHORT_FRAMES), width=SHORT_SIZE[0], height=SHORT_SIZE[1])
        if frames is not None:
            spec = shorten(spec, frames)
        if inst.startswith("ycb_"):
            spec = replace(spec, depth_range=(0.35, 0.6))
        else:  # thin shafts: close enough that the shaft is several pixels wide, as in the paper's recordings
            spec = replace(spec, depth_range=(0.25, 0.5))
        out.append((seq, spec))
    if missing:
        msg = f"suite {name}: real meshes not found (set SURGTRACK_MESHES); skipping {', '.join(missing)}"
        if not out:
            raise FileNotFoundError(msg)
        warnings.warn(msg, stacklevel=2)
    return out


def render_suite(name: str, out_root: Path | str, short: bool = False, frames: int | None = None,
                 progress: Callable[[str, int, int], None] | None = None) -> list[Path]:
    """Render every sequence of a suite (`suite_specs`) under out_root/<sequence>; ones already rendered from the
    same spec are kept as they are. progress(sequence, frame, frames) is called per frame rendered."""
    root = Path(out_root)
    paths = []
    for seq, spec in suite_specs(name, short, frames):
        path = root / seq
        if not is_rendered(spec, path):
            cb = None if progress is None else (lambda i, n, s=seq: progress(s, i, n))
            render_sequence(spec, path, cb)
        paths.append(path)
    return paths
