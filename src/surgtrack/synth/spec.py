"""The typed description of one synthetic sequence (everything that changes its files)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np

SYNTH_VERSION = 1  # bumped whenever the renderer's output for a given spec changes


@dataclass(frozen=True)
class SynthSpec:
    """One synthetic RGB-D sequence. Same spec and seed give byte-identical files."""

    instrument: str = "forceps"  # procedural name, shared real-mesh stem (e.g. dvrk_psm_instrument) or mesh path
    frames: int = 300
    width: int = 640
    height: int = 480
    fps: float = 30.0
    speed: float = 1.0  # motion speed multiplier
    seed: int = 0
    n_occluders: int = 1  # moving hands passing in front (0-3)
    full_occlusions: tuple[tuple[int, int], ...] = ()  # (first frame, length): a hand covers the whole instrument
    fast_segments: tuple[tuple[int, int], ...] = ()  # (first frame, length) of faster motion
    fast_factor: float = 2.5
    noise: bool = True  # RealSense D4xx depth/RGB sensor model; False gives clean depth and colour
    motion_blur: bool = True
    depth_range: tuple[float, float] = (0.25, 0.7)  # metres from the camera to the instrument's focus point
    max_tilt_deg: float = 70.0
    background: str = "auto"  # auto or one of textures.BACKGROUNDS
    hfov_deg: float = 55.0  # horizontal field of view (RealSense D435 colour at 640x480: about 55 degrees)

    def __post_init__(self) -> None:
        if self.frames < 1 or self.width < 16 or self.height < 16:
            raise ValueError(f"invalid size: {self.frames} frames of {self.width}x{self.height}")
        if not 0 <= self.n_occluders <= 3:
            raise ValueError(f"n_occluders must be 0-3, got {self.n_occluders}")
        if not 0.1 <= self.depth_range[0] < self.depth_range[1]:
            raise ValueError(f"invalid depth_range {self.depth_range}")
        if self.speed <= 0 or self.fps <= 0:
            raise ValueError("speed and fps must be positive")
        object.__setattr__(self, "full_occlusions", tuple(tuple(int(x) for x in s) for s in self.full_occlusions))
        object.__setattr__(self, "fast_segments", tuple(tuple(int(x) for x in s) for s in self.fast_segments))
        object.__setattr__(self, "depth_range", tuple(float(x) for x in self.depth_range))

    @property
    def K(self) -> np.ndarray:
        """Pinhole intrinsics (square pixels, principal point at the image centre)."""
        f = 0.5 * self.width / np.tan(np.radians(self.hfov_deg) / 2)
        return np.array([[f, 0.0, (self.width - 1) / 2], [0.0, f, (self.height - 1) / 2], [0.0, 0.0, 1.0]])

    def to_json(self) -> dict:
        d = asdict(self)
        d["full_occlusions"] = [list(s) for s in self.full_occlusions]
        d["fast_segments"] = [list(s) for s in self.fast_segments]
        d["depth_range"] = list(self.depth_range)
        return d

    @classmethod
    def from_json(cls, d: dict) -> SynthSpec:
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def occluded_frames(self) -> np.ndarray:
        """Boolean per frame: inside a full-occlusion stretch."""
        out = np.zeros(self.frames, bool)
        for start, length in self.full_occlusions:
            out[max(0, start) : max(0, start + length)] = True
        return out
