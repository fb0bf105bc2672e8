"""Synthetic Instrument3D/HO3D-like RGB-D sequences with ground truth (a RealSense D4xx seen instrument)."""

from .instruments import PROCEDURAL, Instrument, load_instrument, meshes_dir
from .render import is_rendered, render_sequence
from .spec import SynthSpec
from .suites import SUITES, render_suite, shorten, suite_specs

__all__ = [
    "PROCEDURAL",
    "SUITES",
    "Instrument",
    "SynthSpec",
    "is_rendered",
    "load_instrument",
    "meshes_dir",
    "render_sequence",
    "render_suite",
    "shorten",
    "suite_specs",
]
