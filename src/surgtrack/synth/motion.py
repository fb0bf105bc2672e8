"""Smooth instrument trajectories: full roll about the shaft, large tilts, depth changes, optional fast segments.

The pose is built from the shaft direction in the camera frame (azimuth in the image plane, elevation out of it),
a roll about the shaft, and the camera-frame position of the instrument's focus point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry import make_T
from .instruments import Instrument
from .spec import SynthSpec


@dataclass
class Wave:
    """Sum of sinusoids normalised to [-1, 1]: a smooth, non-periodic-looking signal of time (seconds)."""

    freqs: np.ndarray
    phases: np.ndarray
    amps: np.ndarray

    @classmethod
    def random(cls, rng: np.random.Generator, base_hz: float, n: int = 3) -> Wave:
        freqs = base_hz * rng.uniform(0.6, 1.6, n) * np.array([1.0, 1.9, 3.1][:n])
        amps = np.array([1.0, 0.45, 0.2][:n]) * rng.uniform(0.8, 1.2, n)
        return cls(freqs, rng.uniform(0, 2 * np.pi, n), amps / amps.sum())

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, float)[..., None]
        return (self.amps * np.sin(2 * np.pi * self.freqs * t + self.phases)).sum(-1)


def time_warp(spec: SynthSpec) -> np.ndarray:
    """Motion time (s) of each frame: speed-scaled, running `fast_factor` times faster in fast segments."""
    rate = np.full(spec.frames, spec.speed / spec.fps)
    for start, length in spec.fast_segments:
        rate[max(0, start) : max(0, start + length)] *= spec.fast_factor
    return np.concatenate([[0.0], np.cumsum(rate)[:-1]])


def shaft_rotation(azimuth: float, elevation: float, roll: float) -> np.ndarray:
    """Rotation taking the object's shaft axis (+z) to direction (azimuth, elevation) and rolling it by `roll`."""
    d = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    e1 = np.cross([0.0, 0.0, 1.0], d)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    c, s = np.cos(roll), np.sin(roll)
    return np.stack([c * e1 + s * e2, -s * e1 + c * e2, d], axis=1)


def _axis_frame(axis: np.ndarray) -> np.ndarray:
    """Rotation whose third column is the given object axis (maps canonical shaft +z to it)."""
    a = axis / np.linalg.norm(axis)
    ref = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = ref - (ref @ a) * a
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(a, e1), a], axis=1)


def trajectory(spec: SynthSpec, inst: Instrument, K: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(frames, 4, 4) object-to-camera poses; the instrument's focus point stays inside the view."""
    t = time_warp(spec)
    z_lo, z_hi = spec.depth_range
    if inst.bulky:
        z_lo, z_hi = max(z_lo, 0.32), min(z_hi, 0.62)
    depth = Wave.random(rng, 0.07)
    img_x, img_y = Wave.random(rng, 0.09), Wave.random(rng, 0.08)
    az_w, el_w, roll_w = Wave.random(rng, 0.05), Wave.random(rng, 0.08), Wave.random(rng, 0.06)
    az0 = rng.uniform(-np.pi, np.pi)
    roll_rate = rng.choice([-1.0, 1.0]) * rng.uniform(0.6, 1.0)  # rad/s of steady roll
    roll0 = rng.uniform(0, 2 * np.pi)
    max_tilt = np.radians(spec.max_tilt_deg)
    w, h = spec.width, spec.height
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R_axis = _axis_frame(inst.axis).T  # object axis -> canonical +z
    poses = np.empty((spec.frames, 4, 4))
    for i, ti in enumerate(t):
        z = 0.5 * (z_lo + z_hi) + 0.5 * (z_hi - z_lo) * depth(ti)
        az = az0 + 1.1 * az_w(ti)
        el = 0.5 * max_tilt * (0.35 + 1.65 * el_w(ti)) if not inst.bulky else max_tilt * el_w(ti)
        el = float(np.clip(el, -max_tilt, max_tilt))  # shafts mostly lean away from the camera, down to -0.6 max
        if not inst.bulky:
            # the handle must stay in front of the camera when the shaft points towards it
            length = float(np.ptp((inst.mesh.vertices - inst.focus) @ inst.axis))
            el = max(el, -np.arcsin(min(1.0, max(0.0, (z - 0.12) / max(length, 1e-3)))))
        roll = roll0 + roll_rate * ti + 0.6 * roll_w(ti)
        R = shaft_rotation(az, el, roll) @ R_axis
        # focus point: central part of the image, nudged towards the side where the shaft leaves the view
        shift = 0.0 if inst.bulky else 0.06
        u = cx + (0.22 * img_x(ti) + shift * np.cos(az)) * w
        v = cy + (0.20 * img_y(ti) + shift * np.sin(az)) * h
        p = np.array([(u - cx) / fx * z, (v - cy) / fy * z, z])
        poses[i] = make_T(R, p - R @ inst.focus)
    return poses
