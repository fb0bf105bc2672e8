"""Ray-cast rendering of a synthetic sequence (Open3D RaycastingScene, no display needed) and its ground truth.

Each frame: pose the instrument, hands and table plane in the camera frame, cast one ray per pixel centre
(pixel (u, v) looks along K^-1 [u, v, 1], so t_hit is the z-depth), shade with Blinn-Phong (moving point light with
shadows, camera fill light, an environment term for metal), then apply the RealSense model (sensor.py).
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import trimesh
from scipy.spatial import cKDTree

from ..geometry import inv_T, project, transform
from ..io import SequenceWriter, make_folder
from .instruments import Instrument, Material, load_instrument
from .motion import time_warp, trajectory
from .scene import (
    Background,
    Hand,
    Light,
    cover_pose,
    hand_mesh,
    make_background,
    make_hands,
    make_light,
    skin_material,
)
from .sensor import BASELINE, DepthInputs, motion_blur, realsense_depth, realsense_rgb, tone_map
from .spec import SYNTH_VERSION, SynthSpec
from .textures import sample_texture, srgb_to_linear, tile_fbm, tile_noise

SKIN_TILE_M = 0.25  # metres covered by a hand's skin texture tile
VISIBLE_VOXEL = 0.002  # m, spacing of gt/visible_points.ply
EXPOSURE = 0.5  # fraction of the frame interval the shutter is open (motion blur length)
AE_TARGET, AE_RATE = 0.2, 0.25  # auto exposure: mean linear intensity aimed at, adaptation per frame
COVER_RAMP = 6  # frames a full-occlusion hand takes to slide in and out
INSTRUMENT, BACKGROUND = 0, 1  # geometry ids in every frame's scene; hands follow


@dataclass
class Shaded:
    """A mesh prepared for smooth shading: split-vertex normals and the map to the original faces."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    orig_face: np.ndarray


def prepare(mesh: trimesh.Trimesh) -> Shaded:
    """Split vertices at sharp edges (30 degrees) so normals interpolate smoothly only across smooth surface."""
    s = mesh.smooth_shaded
    _, orig = cKDTree(mesh.triangles_center).query(s.triangles_center)
    return Shaded(np.asarray(s.vertices, np.float64), np.asarray(s.faces, np.uint32),
                  np.asarray(s.vertex_normals, np.float64), np.asarray(orig, np.int64))


def _interp(values: np.ndarray, faces: np.ndarray, prim: np.ndarray, uv: np.ndarray) -> np.ndarray:
    tri = values[faces[prim]]
    w0 = 1 - uv[:, 0] - uv[:, 1]
    return w0[:, None] * tri[:, 0] + uv[:, 0:1] * tri[:, 1] + uv[:, 1:2] * tri[:, 2]


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _normalise(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(np.maximum(_dot(v, v), 1e-20))[:, None]


def skin_texture(mat: Material, rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """Linear-albedo skin: blotchy redness, fine mottling and a few creases, tiled over SKIN_TILE_M."""
    blotch = tile_fbm(rng, size, 5, 3) - 0.5
    mottle = tile_noise(rng, size, size // 3) - 0.5
    crease = np.clip(tile_noise(rng, size, (size // 4, 24)) - 0.75, 0, 1) * 0.25
    base = np.array(mat.albedo, np.float32)
    red = np.array([0.02, -0.05, -0.04], np.float32)
    img = base * (1 + 0.12 * mottle - crease)[..., None] + red * (blotch * 2)[..., None]
    return srgb_to_linear(np.clip(img, 0, 1)).astype(np.float32)


def _env(r: np.ndarray) -> np.ndarray:
    """A blurred room for metal to reflect: bright ceiling with a lamp band, darker walls and floor."""
    up = -r[:, 1]
    sky = np.clip(0.5 + 0.5 * up, 0, 1)
    lamp = np.exp(-(((up - 0.75) / 0.12) ** 2)) * (0.5 + 0.5 * np.cos(3 * np.arctan2(r[:, 0], r[:, 2])))
    val = 0.06 + 0.45 * sky**2 + 1.2 * lamp
    return np.stack([val * 0.97, val, val * 1.03], 1)


class FrameRenderer:
    """Casts and shades one frame; holds the per-sequence constants (rays, meshes, materials)."""

    def __init__(self, spec: SynthSpec, inst: Instrument, hands: list[Hand], bg: Background, light: Light,
                 cover: tuple[trimesh.Trimesh, Material] | None):
        self.spec, self.inst, self.hands, self.bg, self.light = spec, inst, hands, bg, light
        self.K = spec.K
        h, w = spec.height, spec.width
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        self.dirs = np.stack([(u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1], np.ones_like(u)],
                             -1).reshape(-1, 3).astype(np.float32)
        self.rays = np.concatenate([np.zeros_like(self.dirs), self.dirs], 1).astype(np.float32)
        self.inst_mesh = prepare(inst.mesh)
        self.hand_meshes = [prepare(hd.mesh) for hd in hands]
        self.cover = (prepare(cover[0]), cover[1]) if cover is not None else None
        self.bg_v, self.bg_f = bg.mesh()
        self.px_scale = w / 640.0
        self.skin = [skin_texture(hd.material, np.random.default_rng([spec.seed, 31, k])) for k, hd in enumerate(hands)]
        if cover is not None:
            self.skin.append(skin_texture(cover[1], np.random.default_rng([spec.seed, 31, 9])))

    # -------------------------------------------------------------------------------------------- ray casting

    def _scene(self, posed: list[tuple[np.ndarray, np.ndarray]]) -> o3d.t.geometry.RaycastingScene:
        scene = o3d.t.geometry.RaycastingScene()
        for verts, faces in posed:
            scene.add_triangles(o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(faces))
        return scene

    def instrument_bbox(self, T: np.ndarray) -> tuple[float, float, float, float] | None:
        """Pixel box (u0, v0, u1, v1) of the instrument's unoccluded silhouette, or None when out of view."""
        scene = self._scene([(transform(T, self.inst_mesh.vertices), self.inst_mesh.faces)])
        hit = np.isfinite(scene.cast_rays(o3d.core.Tensor(self.rays))["t_hit"].numpy())
        if not hit.any():
            return None
        v, u = np.nonzero(hit.reshape(self.spec.height, self.spec.width))
        return float(u.min()), float(v.min()), float(u.max()), float(v.max())

    def render(self, T: np.ndarray, hand_poses: list[np.ndarray], cover: tuple[np.ndarray, float] | None,
               light_pos: np.ndarray) -> dict[str, np.ndarray]:
        """Clean buffers for one frame: linear colour, z-depth, geometry ids, camera/object points, depth inputs."""
        spec = self.spec
        h, w = spec.height, spec.width
        meshes: list[tuple[Shaded, np.ndarray, float]] = [(self.inst_mesh, T, 1.0)]
        meshes += [(m, P, 1.0) for m, P in zip(self.hand_meshes, hand_poses, strict=True)]
        if cover is not None and self.cover is not None:
            meshes.append((self.cover[0], cover[0], cover[1]))
        posed = [(transform(P, m.vertices * s), m.faces) for m, P, s in meshes]
        posed_n = [m.normals @ P[:3, :3].T for m, P, _ in meshes]
        scene = self._scene([posed[0], (self.bg_v, self.bg_f), *posed[1:]])
        ans = scene.cast_rays(o3d.core.Tensor(self.rays))
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy().astype(np.int64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy()
        hit = np.isfinite(t)
        gid[~hit] = -1
        P = self.dirs * np.where(hit, t, 0.0).astype(np.float32)[:, None]
        n = np.zeros_like(P)
        albedo = np.zeros_like(P)
        ks = np.zeros(len(P), np.float32)
        shin = np.ones(len(P), np.float32)
        metal = np.zeros(len(P), bool)
        ir_drop = np.zeros(len(P), np.float32)
        p_obj = np.zeros(P.shape, np.float64)
        # instrument
        sel = gid == INSTRUMENT
        if sel.any():
            m = self.inst_mesh
            n[sel] = _interp(posed_n[0], m.faces, prim[sel], uv[sel])
            faces = m.orig_face[prim[sel]]
            p_obj[sel] = transform(inv_T(T), P[sel].astype(np.float64))
            albedo[sel] = srgb_to_linear(self.inst.albedo(p_obj[sel], faces))
            mats = self.inst.face_material[faces]
            table = self.inst.materials
            ks[sel] = np.array([x.specular for x in table])[mats]
            shin[sel] = np.array([x.shininess for x in table])[mats]
            metal[sel] = np.array([x.metal for x in table])[mats]
            ir_drop[sel] = np.array([x.ir_dropout for x in table])[mats]
        # background plane
        sel = gid == BACKGROUND
        if sel.any():
            n[sel] = self.bg.normal
            albedo[sel] = sample_texture(self.bg.texture, P[sel] @ self.bg.e1, P[sel] @ self.bg.e2)
            ks[sel], shin[sel] = (0.25, 30.0) if self.bg.kind == "steel_table" else (0.05, 8.0)
            ir_drop[sel] = 0.005
        # hands (and the full-occlusion hand)
        for k in range(1, len(meshes)):
            sel = gid == BACKGROUND + k
            if not sel.any():
                continue
            m, Pk, s = meshes[k]
            mat = self.hands[k - 1].material if k - 1 < len(self.hands) else self.cover[1]  # type: ignore[index]
            n[sel] = _interp(posed_n[k], m.faces, prim[sel], uv[sel])
            local = transform(inv_T(Pk), P[sel].astype(np.float64)) / s
            albedo[sel] = sample_texture(self.skin[k - 1], local[:, 0] + 0.3 * local[:, 2], local[:, 1], SKIN_TILE_M)
            ks[sel], shin[sel], ir_drop[sel] = mat.specular, mat.shininess, mat.ir_dropout
        n = _normalise(n)
        view = -_normalise(P)
        facing = _dot(n, view)
        n[facing < 0] *= -1
        cos_view = np.abs(facing)
        # light with shadows
        to_l = light_pos[None, :] - P
        dist = np.sqrt(_dot(to_l, to_l))
        L = to_l / np.maximum(dist, 1e-9)[:, None]
        origin = P + n * 5e-4
        shadow_rays = np.concatenate([origin, light_pos[None, :] - origin], 1).astype(np.float32)
        occ = scene.test_occlusions(o3d.core.Tensor(shadow_rays), tnear=1e-4, tfar=1.0).numpy() & hit
        lit = (~occ).astype(np.float32) / (1.0 + 0.4 * dist**2)
        ndl = np.clip(_dot(n, L), 0, 1)
        H = _normalise(L + view)
        ndh = np.clip(_dot(n, H), 0, 1)
        spec_term = ks * (shin + 8) / 16 * ndh**shin * (ndl > 0)
        col = self.light.colour[None, :] * lit[:, None] * (albedo * ndl[:, None] + spec_term[:, None])
        col += albedo * (0.22 * cos_view + 0.08 + 0.05 * np.clip(-n[:, 1], 0, 1))[:, None]  # fill + ambient
        if metal.any():
            r = 2 * cos_view[:, None] * n - view
            fres = 0.55 + 0.45 * (1 - cos_view) ** 5
            col[metal] += (ks * fres)[metal, None] * albedo[metal] * _env(r[metal]) * 1.1
        # stereo shadow: visible from the left (reference) imager, hidden from the right one at +BASELINE
        right = np.array([BASELINE, 0.0, 0.0])
        st_rays = np.concatenate([origin, right[None, :] - origin], 1).astype(np.float32)
        stereo = scene.test_occlusions(o3d.core.Tensor(st_rays), tnear=1e-4, tfar=1.0).numpy() & hit
        ir_spec = np.where(metal, cos_view ** np.maximum(shin, 1.0), 0.0) * np.minimum(ks, 1.0)
        return {
            "linear": col.reshape(h, w, 3),
            "z": np.where(hit, P[:, 2], 0.0).reshape(h, w),
            "gid": gid.reshape(h, w),
            "p_obj": p_obj.reshape(h, w, 3),
            "cos_view": cos_view.reshape(h, w),
            "ir_dropout": ir_drop.reshape(h, w),
            "ir_specular": ir_spec.reshape(h, w),
            "stereo_shadow": stereo.reshape(h, w),
            "glare": (metal & (spec_term * lit * self.light.colour.mean() > 1.0)).reshape(h, w),
        }


def _voxel_keys(p: np.ndarray) -> np.ndarray:
    q = np.floor(p / VISIBLE_VOXEL).astype(np.int64) + (1 << 20)
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


class VisibleSurface:
    """Union of the instrument points seen in any frame (object frame), voxel-averaged at VISIBLE_VOXEL."""

    def __init__(self) -> None:
        self.keys = np.zeros(0, np.int64)
        self.sums = np.zeros((0, 3))
        self.counts = np.zeros(0)

    def add(self, p: np.ndarray) -> None:
        if len(p) == 0:
            return
        keys = np.concatenate([self.keys, _voxel_keys(p)])
        sums = np.concatenate([self.sums, p])
        counts = np.concatenate([self.counts, np.ones(len(p))])
        self.keys, inv = np.unique(keys, return_inverse=True)
        self.sums = np.stack([np.bincount(inv, sums[:, k], len(self.keys)) for k in range(3)], 1)
        self.counts = np.bincount(inv, counts, len(self.keys))

    def points(self) -> np.ndarray:
        return self.sums / np.maximum(self.counts, 1)[:, None]


def _cover_schedule(spec: SynthSpec) -> np.ndarray:
    """Per frame, how far the full-occlusion hand has slid in: 1 inside a stretch, ramps either side."""
    frac = np.zeros(spec.frames)
    for start, length in spec.full_occlusions:
        for i in range(spec.frames):
            if start <= i < start + length:
                f = 1.0
            elif start - COVER_RAMP <= i < start:
                f = (i - start + COVER_RAMP + 1) / (COVER_RAMP + 1)
            elif start + length <= i < start + length + COVER_RAMP:
                f = 1 - (i - start - length + 1) / (COVER_RAMP + 1)
            else:
                f = 0.0
            frac[i] = max(frac[i], f)
    return frac


def _prepare_out(out: Path) -> None:
    """Create the folder; clear an earlier synthetic render there, refuse to write over anything else."""
    if any(make_folder(out).iterdir()):
        if not (out / "synth.json").exists() and not (out / "rgb").is_dir():
            raise FileExistsError(f"{out}: folder is not empty and holds no synthetic sequence; not overwriting")
        for sub in ("rgb", "depth", "masks", "gt"):
            if (out / sub).is_dir():
                shutil.rmtree(out / sub)
        for f in ("synth.json", "preview.png", "cam_K.txt"):
            (out / f).unlink(missing_ok=True)


def render_sequence(spec: SynthSpec, out: Path | str, progress: Callable[[int, int], None] | None = None) -> Path:
    """Render `spec` into folder `out` (DESIGN.md section 2 layout with gt/, preview.png, synth.json); returns out."""
    from .preview import write_preview

    out = Path(out)
    inst = load_instrument(spec.instrument)
    _prepare_out(out)
    seeds = np.random.SeedSequence(spec.seed).spawn(3)
    rng_motion, rng_scene = np.random.default_rng(seeds[0]), np.random.default_rng(seeds[1])
    K = spec.K
    poses = trajectory(spec, inst, K, rng_motion)
    times = time_warp(spec)
    bg = make_background(spec.background, rng_scene)
    hands = make_hands(spec.n_occluders, rng_scene, inst.bulky)
    light = make_light(rng_scene)
    cover_frac = _cover_schedule(spec)
    cover = (hand_mesh(rng_scene, 1.0), skin_material(rng_scene)) if cover_frac.any() else None
    cover_side = float(rng_scene.uniform(-np.pi, np.pi))
    renderer = FrameRenderer(spec, inst, hands, bg, light, cover)
    writer = SequenceWriter(out, K)
    visible = VisibleSurface()
    exposure: float | None = None
    for i in range(spec.frames):
        rng = np.random.default_rng([spec.seed, 7919, i])
        T = poses[i]
        focus_cam = transform(T, inst.focus[None, :])[0]
        hand_poses = [hd.pose(times[i], focus_cam) for hd in hands]
        cover_pose_i: tuple[np.ndarray, float] | None = None
        box = renderer.instrument_bbox(T) if cover_frac[i] > 0 else None
        if box is None:
            box = (spec.width / 2 - 10, spec.height / 2 - 10, spec.width / 2 + 10, spec.height / 2 + 10)
        z_near = 0.6 * float(transform(T, inst.mesh.vertices)[:, 2].clip(0.15).min())
        for attempt in range(6):
            if cover_frac[i] > 0:
                grow = 1.3**attempt
                u0, v0, u1, v1 = box
                du, dv = (u1 - u0) * (grow - 1) / 2, (v1 - v0) * (grow - 1) / 2
                cover_pose_i = cover_pose(cover_frac[i], (u0 - du, v0 - dv, u1 + du, v1 + dv), K, z_near, cover_side)
            buf = renderer.render(T, hand_poses, cover_pose_i, light.position(times[i]))
            if cover_frac[i] < 1 or not (buf["gid"] == INSTRUMENT).any():
                break
        mask = buf["gid"] == INSTRUMENT
        if i == 0 and not mask.any():
            raise ValueError(f"{spec.instrument}: the instrument is not in view in the first frame (a sequence of "
                             f"{spec.frames} frames covered from its start?)")
        visible.add(buf["p_obj"][mask])
        # auto exposure: the frame's mean luminance drifts towards a target, as a camera's AE loop does
        wanted = AE_TARGET / max(float(buf["linear"].mean()), 1e-3)
        exposure = wanted if exposure is None else exposure * (wanted / exposure) ** AE_RATE
        exposure = float(np.clip(exposure, 0.4, 3.0))
        display = tone_map(buf["linear"] * exposure)
        if spec.motion_blur and i > 0:
            prev = project(transform(poses[i - 1], inst.focus[None, :]), K)[0][0]
            cur = project(focus_cam[None, :], K)[0][0]
            dx, dy = (cur - prev) * EXPOSURE
            weight = cv2.GaussianBlur(cv2.dilate(mask.astype(np.float32), np.ones((5, 5), np.uint8)), (0, 0), 2.0)
            display = motion_blur(display, np.clip(weight * 1.5, 0, 1), float(dx), float(dy))
        rgb = realsense_rgb(display, rng, renderer.px_scale, spec.noise)
        if spec.noise:
            inputs = DepthInputs(buf["z"], buf["cos_view"], buf["ir_dropout"], buf["ir_specular"], buf["glare"],
                                 buf["stereo_shadow"])
            depth = realsense_depth(inputs, rng, renderer.px_scale)
        else:
            depth = buf["z"].astype(np.float32)
        writer.write_frame(i, rgb, depth, mask, T)
        if progress is not None:
            progress(i + 1, spec.frames)
    writer.write_model(inst.mesh, visible.points())
    write_preview(out, extra=tuple(s + n // 2 for s, n in spec.full_occlusions[:1]))
    record = {"version": SYNTH_VERSION, "spec": spec.to_json()}
    (out / "synth.json").write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")
    return out


def is_rendered(spec: SynthSpec, out: Path | str) -> bool:
    """True when `out` holds a complete render of exactly this spec by this renderer version."""
    p = Path(out) / "synth.json"
    if not p.is_file():
        return False
    try:
        rec = json.loads(p.read_text())
    except json.JSONDecodeError:
        return False
    return rec.get("version") == SYNTH_VERSION and rec.get("spec") == spec.to_json()
