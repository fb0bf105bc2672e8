"""Instruments to render: procedural ones built from trimesh primitives, and any mesh file (metres).

Every instrument has a shaft axis (from the tip towards the handle) in its own object frame; markings (bands, depth
ticks, text-like engraving) are a procedural texture in object coordinates about that axis, so they move with it.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .textures import hash01

MESHES_ENV = "SURGTRACK_MESHES"


@dataclass(frozen=True)
class Material:
    """Blinn-Phong surface; colours are sRGB in [0, 1]."""

    albedo: tuple[float, float, float]
    specular: float = 0.2
    shininess: float = 20.0
    metal: bool = False  # reflects a blurred environment and gives IR specular dropouts
    ir_dropout: float = 0.0  # base probability that stereo matching loses this surface
    marked: bool = False  # carries the instrument's markings
    grain: float = 0.04  # amplitude of fine brushed/moulded albedo variation


@dataclass
class Markings:
    """Procedural markings about the shaft axis: s = distance from the tip along the axis, phi = angle around it."""

    bands: list[tuple[float, float, tuple[float, float, float]]] = field(default_factory=list)  # s0, s1, colour
    ticks: tuple[float, float, float, float, tuple[float, float, float]] | None = None  # s0, s1, pitch, width, colour
    text: list[tuple[float, float, float, float, tuple[float, float, float]]] = field(default_factory=list)
    # text blocks: s0, s1, phi0 (rad), arc height (m), colour; glyphs advance along the axis
    glyph_pitch: float = 0.0045  # m per character along the axis
    seed: int = 0

    def apply(self, s: np.ndarray, phi: np.ndarray, r: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """Albedo (N, 3) with the markings painted at axis coordinates (s, phi, radius r)."""
        out = albedo.copy()
        for s0, s1, col in self.bands:
            sel = (s >= s0) & (s < s1)
            out[sel] = col
        if self.ticks is not None:
            s0, s1, pitch, width, col = self.ticks
            k = np.floor((s - s0) / pitch)
            frac = (s - s0) - k * pitch
            major = np.mod(k, 5) == 0
            arc = np.mod(phi, 2 * np.pi)
            long_enough = np.where(major, arc < 2.2, arc < 0.9)  # tick marks cover part of the circumference
            sel = (s >= s0) & (s < s1) & (frac < np.where(major, 1.8 * width, width)) & long_enough
            out[sel] = col
        for i, (s0, s1, phi0, height, col) in enumerate(self.text):
            arc = np.mod(phi - phi0 + np.pi, 2 * np.pi) - np.pi  # signed angle from the line's centre
            t = arc * np.maximum(r, 1e-4)  # arc length across the line
            inside = (s >= s0) & (s < s1) & (np.abs(t) < height / 2)
            if not inside.any():
                continue
            ss, tt = s[inside] - s0, t[inside] + height / 2
            char = np.floor(ss / self.glyph_pitch).astype(np.int64)
            gx = np.floor((ss - char * self.glyph_pitch) / self.glyph_pitch * 4).astype(np.int64)  # 3 cols + gap
            gy = np.clip(np.floor(tt / height * 5), 0, 4).astype(np.int64)
            space = hash01(char, 99, seed=self.seed + i) < 0.18
            ink = (hash01(char, gx, gy, seed=self.seed + i) < 0.5) & (gx < 3) & ~space
            idx = np.nonzero(inside)[0][ink]
            out[idx] = col
        return out


@dataclass
class Instrument:
    """A renderable object: mesh in its own frame (metres), per-face materials and the shaft axis."""

    name: str
    mesh: trimesh.Trimesh
    face_material: np.ndarray
    materials: list[Material]
    tip: np.ndarray  # object-frame point at the distal end
    axis: np.ndarray  # unit vector from the tip towards the handle
    focus: np.ndarray  # object-frame point the trajectory moves (the part a camera looks at)
    markings: Markings
    bulky: bool = False  # a hand-held object (HO3D-like) rather than a shaft instrument

    def axis_coords(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(s, phi, r): distance along the axis from the tip, angle around it, distance from it."""
        d = p - self.tip
        s = d @ self.axis
        ref = np.array([1.0, 0.0, 0.0]) if abs(self.axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        e1 = ref - (ref @ self.axis) * self.axis
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(self.axis, e1)
        x, y = d @ e1, d @ e2
        return s, np.arctan2(y, x), np.hypot(x, y)

    def albedo(self, p_obj: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """sRGB albedo (N, 3) at object-frame surface points lying on the given faces."""
        mat_idx = self.face_material[faces]
        base = np.array([m.albedo for m in self.materials])[mat_idx]
        grain = np.array([m.grain for m in self.materials])[mat_idx]
        s, phi, r = self.axis_coords(p_obj)
        # fine streaks along the axis (brushed metal, extruded plastic) keyed on the angle around it
        streak = hash01(np.floor(phi * 180).astype(np.int64), seed=self.markings.seed + 5) - 0.5
        speck = hash01(np.floor(s * 2000).astype(np.int64), np.floor(phi * 90).astype(np.int64), seed=17) - 0.5
        base = base * (1 + grain[:, None] * (1.6 * streak + 0.8 * speck)[:, None])
        marked = np.array([m.marked for m in self.materials])[mat_idx]
        if marked.any():
            base[marked] = self.markings.apply(s[marked], phi[marked], r[marked], base[marked])
        return np.clip(base, 0, 1)


# ------------------------------------------------------------------------------------------------ materials

STEEL = Material((0.62, 0.63, 0.65), specular=0.9, shininess=90, metal=True, ir_dropout=0.04, marked=True)
STEEL_TIP = Material((0.70, 0.70, 0.70), specular=1.0, shininess=120, metal=True, ir_dropout=0.06, grain=0.06)
SATIN = Material((0.50, 0.51, 0.53), specular=0.55, shininess=40, metal=True, ir_dropout=0.03, marked=True)
BLACK_SHAFT = Material((0.07, 0.07, 0.08), specular=0.45, shininess=45, ir_dropout=0.10, marked=True)
BLACK_PLASTIC = Material((0.09, 0.09, 0.10), specular=0.3, shininess=25, ir_dropout=0.08, grain=0.08)
GREY_PLASTIC = Material((0.55, 0.56, 0.58), specular=0.25, shininess=18, grain=0.05)
WHITE_PLASTIC = Material((0.80, 0.80, 0.78), specular=0.3, shininess=20, grain=0.03)
BLUE_PLASTIC = Material((0.12, 0.30, 0.62), specular=0.35, shininess=25, grain=0.05)
GLASS = Material((0.03, 0.04, 0.06), specular=1.0, shininess=200, ir_dropout=0.6, grain=0.0)
RUBBER = Material((0.16, 0.16, 0.17), specular=0.1, shininess=8, ir_dropout=0.05, grain=0.10)
TEAL_PLASTIC = Material((0.10, 0.33, 0.36), specular=0.35, shininess=25, grain=0.05, marked=True)
YELLOW_PLASTIC = Material((0.93, 0.76, 0.08), specular=0.4, shininess=30, grain=0.03, marked=True)

WHITE, BLACK, YELLOW = (0.92, 0.92, 0.90), (0.03, 0.03, 0.03), (0.95, 0.78, 0.10)


# ------------------------------------------------------------------------------------------------ primitives


def _along(mesh: trimesh.Trimesh, start: np.ndarray, direction: np.ndarray) -> trimesh.Trimesh:
    """Move a mesh built along +z from the origin so it starts at `start` and runs along `direction`."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    T = trimesh.geometry.align_vectors([0, 0, 1], d)
    T[:3, 3] = start
    return mesh.copy().apply_transform(T)


def revolved(profile: list[tuple[float, float]], sections: int = 32) -> trimesh.Trimesh:
    """Closed surface of revolution about +z from (radius, z) pairs listed from the bottom axis point upwards."""
    pts = np.array([(0.0, profile[0][1]), *profile, (0.0, profile[-1][1])])
    return trimesh.creation.revolve(pts, sections=sections)


def tube(path: np.ndarray, radius: float, sections: int = 20) -> trimesh.Trimesh:
    """A capped tube of constant radius along a polyline (parallel-transport frames)."""
    path = np.asarray(path, float)
    tang = np.gradient(path, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    ref = np.array([1.0, 0.0, 0.0]) if abs(tang[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    n = np.cross(tang[0], ref)
    n /= np.linalg.norm(n)
    rings = []
    ang = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    for i, t in enumerate(tang):
        if i:
            n = n - (n @ t) * t
            n /= np.linalg.norm(n)
        b = np.cross(t, n)
        rings.append(path[i] + radius * (np.cos(ang)[:, None] * n + np.sin(ang)[:, None] * b))
    verts = np.concatenate([np.concatenate(rings), path[[0, -1]]])
    faces = []
    m = len(path)
    for i in range(m - 1):
        for j in range(sections):
            a, b2 = i * sections + j, i * sections + (j + 1) % sections
            c, d = a + sections, b2 + sections
            faces += [[a, b2, d], [a, d, c]]
    c0, c1 = m * sections, m * sections + 1
    for j in range(sections):
        faces.append([c0, (j + 1) % sections, j])
        last = (m - 1) * sections
        faces.append([c1, last + j, last + (j + 1) % sections])
    mesh = trimesh.Trimesh(verts, np.array(faces), process=False)
    mesh.fix_normals()
    return mesh


def _assemble(parts: list[tuple[trimesh.Trimesh, Material]]) -> tuple[trimesh.Trimesh, np.ndarray, list[Material]]:
    materials: list[Material] = []
    ids = []
    for mesh, mat in parts:
        if mat not in materials:
            materials.append(mat)
        ids.append(np.full(len(mesh.faces), materials.index(mat)))
    mesh = trimesh.util.concatenate([m for m, _ in parts])
    return mesh, np.concatenate(ids), materials


def _shaft_instrument(name: str, parts: list[tuple[trimesh.Trimesh, Material]], markings: Markings,
                      focus_s: float) -> Instrument:
    mesh, fm, mats = _assemble(parts)
    axis = np.array([0.0, 0.0, 1.0])
    tip = np.zeros(3)
    return Instrument(name, mesh, fm, mats, tip, axis, tip + focus_s * axis, markings)


# ------------------------------------------------------------------------------------------------ procedural


def rigid_endoscope() -> Instrument:
    """10 mm rigid laparoscope: steel shaft, glass window, eyepiece housing, light post."""
    r = 0.005
    shaft = revolved([(r * 0.92, 0.0), (r, 0.0015), (r, 0.30), (0.0075, 0.305)], 40)
    window = revolved([(r * 0.7, -0.0004), (r * 0.7, 0.0)], 24)
    body = revolved([(0.0075, 0.305), (0.012, 0.315), (0.012, 0.36), (0.0105, 0.362), (0.0105, 0.372)], 40)
    cup = revolved([(0.016, 0.372), (0.017, 0.378), (0.017, 0.392), (0.012, 0.394)], 40)
    post = _along(revolved([(0.0035, 0.0), (0.0035, 0.02), (0.0055, 0.021), (0.0055, 0.032)], 20),
                  np.array([0.0, 0.0, 0.335]), np.array([1.0, 0.0, 0.0]))
    marks = Markings(
        bands=[(0.012, 0.016, BLACK), (0.2005, 0.2025, BLACK), (0.206, 0.208, BLACK)],
        ticks=(0.03, 0.20, 0.01, 0.0012, BLACK),
        text=[(0.215, 0.29, 0.4, 0.0045, BLACK), (0.24, 0.28, 3.0, 0.004, BLACK)],
        seed=11,
    )
    parts = [(shaft, STEEL), (window, GLASS), (body, SATIN), (cup, BLACK_PLASTIC), (post, STEEL_TIP)]
    return _shaft_instrument("rigid_endoscope", parts, marks, 0.07)


def thoracoscope() -> Instrument:
    """Short 10 mm thoracoscope with a bulky camera head and cable."""
    r = 0.005
    shaft = revolved([(r * 0.9, 0.0), (r, 0.002), (r, 0.19), (0.007, 0.195)], 40)
    window = revolved([(r * 0.75, -0.0004), (r * 0.75, 0.0)], 24)
    coupler = revolved([(0.007, 0.195), (0.014, 0.2), (0.014, 0.225), (0.018, 0.228), (0.018, 0.24)], 40)
    head = revolved([(0.018, 0.24), (0.021, 0.25), (0.021, 0.31), (0.016, 0.325), (0.006, 0.33)], 40)
    buttons = [(_along(revolved([(0.004, 0.0), (0.004, 0.006)], 16), np.array([0.0, 0.019, z]),
                       np.array([0.0, 1.0, 0.0])), GREY_PLASTIC) for z in (0.262, 0.277)]
    cable = tube(np.stack([np.zeros(12), -0.004 * np.arange(12) ** 1.6, 0.33 + 0.012 * np.arange(12)], 1), 0.004)
    marks = Markings(
        bands=[(0.006, 0.010, WHITE), (0.13, 0.134, BLACK), (0.137, 0.139, BLACK)],
        ticks=(0.02, 0.12, 0.01, 0.0011, BLACK),
        text=[(0.142, 0.185, 1.2, 0.0045, BLACK)],
        seed=23,
    )
    parts = [(shaft, STEEL), (window, GLASS), (coupler, SATIN), (head, BLUE_PLASTIC),
             *buttons, (cable, BLACK_PLASTIC)]
    return _shaft_instrument("thoracoscope", parts, marks, 0.06)


def ultrasound_probe() -> Instrument:
    """Laparoscopic ultrasound probe: flat transducer head on a 10 mm shaft, grey handle with cable."""
    r = 0.005
    head = trimesh.creation.capsule(height=0.032, radius=0.0055, count=[24, 12])
    head.apply_scale([1.25, 0.85, 1.0])
    head.apply_translation([0.0, 0.0, 0.022])
    window = trimesh.creation.box([0.006, 0.002, 0.028])
    window.apply_translation([0.0, -0.0045, 0.022])
    neck = revolved([(0.0045, 0.038), (0.0045, 0.05), (r, 0.052)], 32)
    shaft = revolved([(r, 0.052), (r, 0.33), (0.009, 0.34)], 40)
    handle = revolved([(0.009, 0.34), (0.016, 0.355), (0.018, 0.40), (0.016, 0.45), (0.008, 0.46)], 40)
    cable = revolved([(0.004, 0.46), (0.004, 0.56)], 16)
    marks = Markings(
        bands=[(0.052, 0.056, BLACK), (0.09, 0.094, YELLOW), (0.25, 0.255, BLACK)],
        ticks=(0.10, 0.24, 0.01, 0.0012, WHITE),
        text=[(0.06, 0.085, 2.0, 0.004, WHITE), (0.258, 0.31, 0.5, 0.0045, WHITE)],
        seed=37,
    )
    parts = [(head, GREY_PLASTIC), (window, RUBBER), (neck, RUBBER), (shaft, BLACK_SHAFT),
             (handle, GREY_PLASTIC), (cable, BLACK_PLASTIC)]
    return _shaft_instrument("ultrasound_probe", parts, marks, 0.06)


def forceps() -> Instrument:
    """5 mm laparoscopic grasper: open steel jaws, black insulated shaft, rotation knob and ring handle."""
    r = 0.0025
    hinge = revolved([(0.0022, 0.014), (r, 0.017), (r, 0.024)], 24)
    jaws = []
    for sign in (1.0, -1.0):
        jaw = trimesh.creation.box([0.0042, 0.0016, 0.017])
        jaw.apply_translation([0.0, 0.0, -0.0085])
        rot = trimesh.transformations.rotation_matrix(np.radians(14) * sign, [1, 0, 0])
        rot[:3, 3] = [0.0, 0.0011 * sign, 0.016]
        jaws.append((jaw.apply_transform(rot), STEEL_TIP))
    shaft = revolved([(r, 0.024), (r, 0.33), (0.004, 0.333)], 32)
    knob = revolved([(0.004, 0.333), (0.010, 0.336), (0.011, 0.345), (0.009, 0.35), (0.006, 0.352)], 32)
    housing = trimesh.creation.box([0.016, 0.05, 0.05])
    housing.apply_translation([0.0, -0.012, 0.375])
    grip = _along(trimesh.creation.box([0.012, 0.012, 0.09]), np.array([0.0, -0.02, 0.395]),
                  np.array([0.0, -0.8, 0.6]))
    ring = trimesh.creation.torus(0.014, 0.004, 32, 12)
    ring.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    ring.apply_translation([0.0, -0.085, 0.44])
    trigger = _along(trimesh.creation.box([0.01, 0.01, 0.075]), np.array([0.0, -0.03, 0.37]),
                     np.array([0.0, -0.95, -0.3]))
    ring2 = trimesh.creation.torus(0.012, 0.004, 32, 12)
    ring2.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    ring2.apply_translation([0.0, -0.11, 0.345])
    marks = Markings(
        bands=[(0.024, 0.027, WHITE), (0.20, 0.203, WHITE), (0.206, 0.208, WHITE)],
        ticks=(0.04, 0.19, 0.01, 0.0010, WHITE),
        text=[(0.215, 0.30, 0.3, 0.0035, WHITE)],
        glyph_pitch=0.004,
        seed=53,
    )
    parts = [(hinge, STEEL_TIP), *jaws, (shaft, BLACK_SHAFT), (knob, BLUE_PLASTIC), (housing, BLACK_PLASTIC),
             (grip, BLACK_PLASTIC), (ring, BLACK_PLASTIC), (trigger, BLACK_PLASTIC), (ring2, BLACK_PLASTIC)]
    return _shaft_instrument("forceps", parts, marks, 0.05)


def bronchoscope() -> Instrument:
    """Flexible endoscope: 5.6 mm black insertion tube with a bent distal section, control body with lever."""
    r = 0.0028
    bend = np.radians(np.linspace(0, 70, 12))
    rb = 0.05  # bending radius
    distal = np.stack([rb * (1 - np.cos(bend)), np.zeros_like(bend), rb * np.sin(bend)], 1)[::-1]
    distal = distal - distal[0]
    end = distal[-1]
    straight = end + np.outer(np.linspace(0.01, 0.26, 10), [0.0, 0.0, 1.0])
    path = np.concatenate([distal, straight])
    ins = tube(path, r, 20)
    tip_cap = _along(revolved([(0.0026, 0.0), (0.0029, 0.0008), (0.0029, 0.007)], 20), path[0],
                     path[0] - path[1])
    z0 = path[-1, 2]
    x0 = path[-1, 0]
    strain = _along(revolved([(0.0035, 0.0), (0.006, 0.03), (0.009, 0.04)], 24), np.array([x0, 0, z0]),
                    np.array([0, 0, 1.0]))
    body = _along(revolved([(0.009, 0.0), (0.017, 0.01), (0.017, 0.09), (0.014, 0.11), (0.012, 0.14)], 32),
                  np.array([x0, 0, z0 + 0.04]), np.array([0, 0, 1.0]))
    lever = _along(trimesh.creation.box([0.006, 0.016, 0.035]), np.array([x0, 0.02, z0 + 0.18]),
                   np.array([0.0, 0.5, 1.0]))
    port = _along(revolved([(0.004, 0.0), (0.004, 0.02), (0.006, 0.021), (0.006, 0.027)], 16),
                  np.array([x0, 0.012, z0 + 0.06]), np.array([0.0, 1.0, 0.4]))
    marks = Markings(
        bands=[(0.0, 0.007, (0.2, 0.2, 0.2)), (0.045, 0.05, WHITE)],
        ticks=(0.06, 0.30, 0.01, 0.0011, WHITE),
        text=[(0.012, 0.04, 0.0, 0.0035, WHITE), (0.2, 0.25, 2.5, 0.0035, WHITE)],
        glyph_pitch=0.004,
        seed=71,
    )
    flex = Material((0.05, 0.05, 0.055), specular=0.55, shininess=50, ir_dropout=0.08, marked=True)
    parts = [(ins, flex), (tip_cap, STEEL_TIP), (strain, RUBBER), (body, GREY_PLASTIC), (lever, BLACK_PLASTIC),
             (port, WHITE_PLASTIC)]
    mesh, fm, mats = _assemble(parts)
    # markings follow the straight part's axis; the bent part keeps its tube surface but shares the pattern
    tip = path[0]
    axis = np.array([0.0, 0.0, 1.0])
    return Instrument("bronchoscope", mesh, fm, mats, tip, axis, tip + 0.05 * axis + np.array([0.02, 0, 0]), marks)


PROCEDURAL: dict[str, Callable[[], Instrument]] = {
    "rigid_endoscope": rigid_endoscope,
    "thoracoscope": thoracoscope,
    "ultrasound_probe": ultrasound_probe,
    "forceps": forceps,
    "bronchoscope": bronchoscope,
}


# ------------------------------------------------------------------------------------------------ mesh files

# Appearance of the shared real meshes: shaft material, body material, bulky (HO3D-like) or not.
REAL_APPEARANCE: dict[str, tuple[Material, Material, bool]] = {
    "dvrk_psm_instrument": (SATIN, GREY_PLASTIC, False),
    "dvrk_instrument_shaft_hires": (SATIN, GREY_PLASTIC, False),
    "dvrk_instrument_housing": (GREY_PLASTIC, GREY_PLASTIC, True),
    "dvrk_endoscope": (STEEL, BLACK_PLASTIC, False),
    "si_endoscope": (STEEL, WHITE_PLASTIC, False),
    "ycb_power_drill": (TEAL_PLASTIC, BLACK_PLASTIC, True),
    "ycb_mustard_bottle": (YELLOW_PLASTIC, YELLOW_PLASTIC, True),
}


def meshes_dir() -> Path | None:
    """The shared real-mesh folder: $SURGTRACK_MESHES, else ../shared/data/meshes beside the repository."""
    env = os.environ.get(MESHES_ENV)
    if env:
        return Path(env) if Path(env).is_dir() else None
    here = Path(__file__).resolve()
    for base in (here.parents[3].parent, Path.cwd().parent, Path.cwd()):
        cand = base / "shared" / "data" / "meshes"
        if cand.is_dir():
            return cand
    return None


def resolve_mesh(name: str) -> Path | None:
    """Path of a mesh given as a file path or as the stem of a shared real mesh; None when not found."""
    p = Path(name).expanduser()
    if p.suffix and p.is_file():
        return p
    d = meshes_dir()
    if d is not None and (d / f"{name}.ply").is_file():
        return d / f"{name}.ply"
    return None


def needs_mesh_file(name: str) -> bool:
    """True when the instrument is not procedural (a mesh file is required)."""
    return name not in PROCEDURAL


def _principal_axis(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = v.mean(0)
    _, _, vt = np.linalg.svd(v - c, full_matrices=False)
    return c, vt[0]


def from_mesh(path: Path, name: str | None = None) -> Instrument:
    """Instrument from a mesh file: shaft axis by PCA, tip at the thinner end, materials by radius."""
    from ..io import load_mesh

    mesh = load_mesh(path)
    name = name or path.stem
    shaft_mat, body_mat, bulky = REAL_APPEARANCE.get(name, (SATIN, GREY_PLASTIC, False))
    v = np.asarray(mesh.vertices, float)
    c, a = _principal_axis(v)
    a = a / np.linalg.norm(a)
    major = np.argmax(np.abs(a))
    if np.abs(a[major]) > 0.95:  # snap to a mesh axis when it is one (all shared meshes)
        a = np.sign(a[major]) * np.eye(3)[major]
    s = (v - c) @ a
    radial = np.linalg.norm((v - c) - np.outer(s, a), axis=1)
    lo, hi = s.min(), s.max()
    span = hi - lo
    r_lo = radial[s < lo + 0.1 * span].max(initial=0.0)
    r_hi = radial[s > hi - 0.1 * span].max(initial=0.0)
    if bulky:
        axis, tip = a, c + lo * a  # s runs from the bottom of the object upwards
    else:
        axis = a if r_lo < r_hi else -a  # from the thin end (tip) towards the body
        tip = c + (lo * a if axis @ a > 0 else hi * a)
    fc = mesh.triangles_center
    fs = (fc - tip) @ axis
    fr = np.linalg.norm((fc - tip) - np.outer(fs, axis), axis=1)
    if bulky:
        face_mat = np.zeros(len(mesh.faces), int)
        mats = [shaft_mat]
        if body_mat != shaft_mat:
            # the lowest part (drill handle/battery, bottle cap) in the body material
            face_mat[fs < 0.3 * (fs.max() - fs.min()) + fs.min()] = 1
            mats.append(body_mat)
        length = float(fs.max())
        marks = Markings(
            bands=[(0.35 * length, 0.37 * length, BLACK)],
            text=[(0.45 * length, 0.8 * length, phi, 0.012, col)
                  for phi, col in ((0.0, (0.75, 0.1, 0.1)), (1.4, BLACK), (2.6, (0.1, 0.2, 0.6)), (4.0, WHITE))],
            glyph_pitch=0.008,
            seed=91,
        )
        focus = c.copy()
        return Instrument(name, mesh, face_mat, mats, tip, axis, focus, marks, bulky=True)
    shaft_r = float(np.median(fr[(fs > 0.15 * span) & (fs < 0.5 * span)])) if len(fs) else 0.005
    face_mat = np.ones(len(mesh.faces), int)
    face_mat[(fr < 1.6 * shaft_r + 1e-3)] = 0
    face_mat[fs < 0.012] = 2
    mats = [shaft_mat, body_mat, STEEL_TIP]
    marks = Markings(
        bands=[(0.02, 0.024, BLACK), (0.15, 0.153, BLACK), (0.156, 0.158, BLACK)],
        ticks=(0.03, 0.14, 0.01, 0.0012, BLACK),
        text=[(0.165, 0.24, 0.3, 0.0045, BLACK), (0.18, 0.22, 2.8, 0.004, (0.6, 0.1, 0.1))],
        seed=29,
    )
    return Instrument(name, mesh, face_mat, mats, tip, axis, tip + 0.06 * axis, marks)


def load_instrument(name: str) -> Instrument:
    """A procedural instrument by name, a shared real mesh by stem, or any mesh file path."""
    if name in PROCEDURAL:
        return PROCEDURAL[name]()
    path = resolve_mesh(name)
    if path is None:
        known = ", ".join(sorted(PROCEDURAL))
        raise FileNotFoundError(
            f"{name}: not a procedural instrument ({known}), a mesh file, or a mesh in the shared folder "
            f"(set {MESHES_ENV} to the folder holding the real meshes)"
        )
    return from_mesh(path, path.stem)
