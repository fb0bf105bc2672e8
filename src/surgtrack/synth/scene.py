"""Everything around the instrument: a textured table/drape plane, moving hands that occlude it, a moving light."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from ..geometry import make_T
from .instruments import Material
from .motion import Wave
from .textures import BACKGROUNDS, background_texture

SKIN_TONES = ((0.87, 0.67, 0.56), (0.78, 0.57, 0.45), (0.62, 0.43, 0.32), (0.92, 0.76, 0.66))
GLOVES = ((0.55, 0.62, 0.86), (0.93, 0.88, 0.74))  # nitrile blue, latex cream


@dataclass
class Background:
    """An infinite-looking plane n . x = offset behind the instrument, with a texture in plane coordinates."""

    normal: np.ndarray
    offset: float
    e1: np.ndarray
    e2: np.ndarray
    texture: np.ndarray  # linear albedo image, see textures.background_texture
    kind: str

    def mesh(self, half: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
        c = self.normal * self.offset
        corners = [c + half * (a * self.e1 + b * self.e2) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        return np.array(corners, np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32)


def make_background(kind: str, rng: np.random.Generator) -> Background:
    if kind == "auto":
        kind = str(rng.choice(BACKGROUNDS))
    if kind not in BACKGROUNDS:
        raise ValueError(f"unknown background {kind!r}; choose auto or one of {', '.join(BACKGROUNDS)}")
    tilt = np.radians(rng.uniform(12, 28))  # the camera looks down onto a table
    yaw = np.radians(rng.uniform(-10, 10))
    n = np.array([np.sin(yaw), np.sin(tilt), -np.cos(tilt) * np.cos(yaw)])
    n /= np.linalg.norm(n)  # points from the plane towards the camera
    offset = -rng.uniform(1.05, 1.25)  # n . x = offset, camera at x = 0 in front of it
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    return Background(n, offset, e1, e2, background_texture(kind, rng), kind)


# ------------------------------------------------------------------------------------------------ hands


def hand_mesh(rng: np.random.Generator, scale: float = 1.0) -> trimesh.Trimesh:
    """A hand with forearm in its own frame: wrist at the origin, fingers along +y, palm facing -z (the camera)."""
    parts = []
    palm = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    palm.apply_scale([0.044, 0.052, 0.015])
    palm.apply_translation([0.0, 0.05, 0.0])
    parts.append(palm)
    arm = trimesh.creation.capsule(height=0.28, radius=0.025, count=[24, 12])
    arm.apply_scale([1.0, 1.0, 1.0])
    arm.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    arm.apply_translation([0.0, -0.15, 0.004])
    arm.vertices[:, 0] *= 1.15
    arm.vertices[:, 2] *= 0.8
    parts.append(arm)
    lengths = np.array([0.068, 0.076, 0.072, 0.058]) * rng.uniform(0.92, 1.08)
    curl = rng.uniform(0.0, 0.9)
    spread = rng.uniform(0.0, 0.06)
    for k, (x, length) in enumerate(zip((-0.028, -0.0095, 0.0095, 0.027), lengths, strict=True)):
        r = 0.0093 - 0.0008 * abs(k - 1.5)
        base = np.array([x, 0.092, 0.0])
        ang = spread * (k - 1.5)
        a = np.array([np.sin(ang), np.cos(ang), 0.0])
        # two phalanx segments: the second curls towards the palm side (+z away from camera)
        seg1 = 0.55 * length
        mid = base + a * seg1
        b = np.array([a[0] * np.cos(curl), a[1] * np.cos(curl), np.sin(curl)])
        tip = mid + b * (length - seg1)
        for p0, p1, rad in ((base, mid, r), (mid, tip, 0.92 * r)):
            seg = trimesh.creation.capsule(height=float(np.linalg.norm(p1 - p0)), radius=rad, count=[16, 8])
            T = trimesh.geometry.align_vectors([0, 0, 1], p1 - p0)
            T[:3, 3] = (p0 + p1) / 2
            parts.append(seg.apply_transform(T))
    thumb_base = np.array([-0.038, 0.035, -0.004])
    ta = np.array([-0.75, 0.62, -0.2])
    ta /= np.linalg.norm(ta)
    thumb = trimesh.creation.capsule(height=0.052, radius=0.0105, count=[16, 8])
    T = trimesh.geometry.align_vectors([0, 0, 1], ta)
    T[:3, 3] = thumb_base + ta * 0.026
    parts.append(thumb.apply_transform(T))
    mesh = trimesh.util.concatenate(parts)
    mesh.apply_scale(scale)
    return mesh


@dataclass
class Hand:
    """A hand passing in front of the instrument: it reaches in from one side of the image and wanders."""

    mesh: trimesh.Trimesh
    material: Material
    reach: Wave
    side: Wave
    lift: Wave
    twist: Wave
    direction: float  # image-plane direction (rad) the forearm comes from
    depth_gap: float  # metres in front of the instrument's focus point
    max_reach: float
    cover: bool = False  # a full-occlusion hand

    def pose(self, t: float, focus_cam: np.ndarray) -> np.ndarray:
        """Hand-to-camera pose at motion time t, given the instrument focus point in the camera frame."""
        d = self.direction + 0.35 * self.side(t)
        inward = -np.array([np.cos(d), np.sin(d), 0.0])  # fingers point from outside towards the focus
        reach = self.max_reach * (0.66 + 0.34 * self.reach(t))  # wrist distance from the focus point
        z = max(0.14, focus_cam[2] - self.depth_gap * (1 + 0.3 * self.lift(t)))
        wrist = focus_cam * (z / focus_cam[2]) - inward * reach
        wrist[2] = z
        return _hand_frame(inward, 0.5 * self.twist(t), wrist)


def _hand_frame(fingers: np.ndarray, twist: float, origin: np.ndarray) -> np.ndarray:
    y = fingers / np.linalg.norm(fingers)
    z = np.array([0.0, 0.0, 1.0])  # palm normal roughly along the optical axis, rolled by `twist` about y
    z = z - (z @ y) * y
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    c, s = np.cos(twist), np.sin(twist)
    x, z = c * x + s * z, -s * x + c * z
    return make_T(np.stack([x, y, z], axis=1), origin)


def skin_material(rng: np.random.Generator) -> Material:
    gloved = rng.uniform() < 0.3
    col = GLOVES[int(rng.integers(len(GLOVES)))] if gloved else SKIN_TONES[int(rng.integers(len(SKIN_TONES)))]
    return Material(tuple(float(c) for c in col), specular=0.25 if gloved else 0.12, shininess=30 if gloved else 10,
                    ir_dropout=0.02, grain=0.05)


def make_hands(n: int, rng: np.random.Generator, bulky: bool) -> list[Hand]:
    hands = []
    for k in range(n):
        spread = 2 * np.pi * k / n + rng.normal(0, 0.3)
        direction = rng.uniform(-np.pi, np.pi) if k == 0 else hands[0].direction + spread
        hands.append(Hand(
            mesh=hand_mesh(rng, rng.uniform(0.9, 1.1)),
            material=skin_material(rng),
            reach=Wave.random(rng, 0.12),
            side=Wave.random(rng, 0.07),
            lift=Wave.random(rng, 0.1),
            twist=Wave.random(rng, 0.08),
            direction=float(direction),
            depth_gap=rng.uniform(0.02, 0.05) if not bulky else rng.uniform(0.04, 0.07),
            max_reach=rng.uniform(0.24, 0.32),
        ))
    return hands


def cover_pose(frac: float, bbox_px: tuple[float, float, float, float], K: np.ndarray, z_near: float,
               side: float) -> tuple[np.ndarray, float]:
    """Pose and scale of a hand whose palm covers an image box fully at frac = 1 and slides in from `side`.

    The palm (semi-axes 42 x 50 mm at scale 1, centred 5 cm up the hand) is placed at depth z so that its
    projection covers the box's circumscribed circle with margin; closer than 10 cm it is scaled up instead.
    """
    u0, v0, u1, v1 = bbox_px
    f = K[0, 0]
    radius_px = 0.5 * np.hypot(u1 - u0 + 4, v1 - v0 + 4) * 1.25
    z = min(z_near, max(0.1, 0.042 * f / radius_px))
    scale = max(1.0, radius_px * z / (0.042 * f))
    uc, vc = (u0 + u1) / 2, (v0 + v1) / 2
    palm_c = np.array([(uc - K[0, 2]) / f * z, (vc - K[1, 2]) / K[1, 1] * z, z])
    out = np.array([np.cos(side), np.sin(side), 0.0])
    # slide in from outside the view along `side`
    e = (1 - frac) ** 2
    palm_c = palm_c + out * e * (0.8 * z + 0.2)
    fingers = -out
    wrist = palm_c - fingers * 0.05 * scale
    return _hand_frame(fingers, 0.0, wrist), scale


@dataclass
class Light:
    """A point light circling above the scene (key light) plus a weak fill from the camera."""

    centre: np.ndarray
    radius: float
    wave: Wave
    phase: float
    colour: np.ndarray  # linear RGB intensity

    def position(self, t: float) -> np.ndarray:
        a = self.phase + 0.25 * t + 0.8 * self.wave(t)
        return self.centre + self.radius * np.array([np.cos(a), 0.3 * np.sin(2 * a), np.sin(a)])


def make_light(rng: np.random.Generator) -> Light:
    warm = rng.uniform(0.0, 0.12)
    return Light(
        centre=np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.75, -0.5), rng.uniform(0.1, 0.3)]),
        radius=rng.uniform(0.25, 0.45),
        wave=Wave.random(rng, 0.05),
        phase=rng.uniform(0, 2 * np.pi),
        colour=np.array([1.0 + warm, 1.0, 1.0 - warm]) * rng.uniform(2.6, 3.2),
    )
