"""Procedural textures: integer hashing, value noise and background images, all deterministic from a seed."""

from __future__ import annotations

import cv2
import numpy as np

_M1, _M2, _M3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def hash01(*keys: np.ndarray, seed: int = 0) -> np.ndarray:
    """Uniform [0, 1) value for each tuple of integer keys (splitmix64 finaliser), broadcast over the keys."""
    with np.errstate(over="ignore"):
        h = np.uint64(seed) * _M1 + np.uint64(0x632BE59BD9B4E019)
        for k in keys:
            h = h ^ (np.asarray(k).astype(np.int64).astype(np.uint64) + _M1 + (h << np.uint64(6)) + (h >> np.uint64(2)))
            h = (h ^ (h >> np.uint64(30))) * _M2
            h = (h ^ (h >> np.uint64(27))) * _M3
            h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def value_noise2(x: np.ndarray, y: np.ndarray, seed: int = 0) -> np.ndarray:
    """Smooth 2D value noise in [0, 1] on a unit lattice."""
    xi, yi = np.floor(x), np.floor(y)
    fx, fy = x - xi, y - yi
    sx, sy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    xi, yi = xi.astype(np.int64), yi.astype(np.int64)
    a, b = hash01(xi, yi, seed=seed), hash01(xi + 1, yi, seed=seed)
    c, d = hash01(xi, yi + 1, seed=seed), hash01(xi + 1, yi + 1, seed=seed)
    return (a + (b - a) * sx) * (1 - sy) + (c + (d - c) * sx) * sy


def fbm2(x: np.ndarray, y: np.ndarray, octaves: int = 4, seed: int = 0) -> np.ndarray:
    """Fractal sum of value noise, roughly in [0, 1]."""
    total, amp, norm = np.zeros_like(x, dtype=np.float64), 1.0, 0.0
    for o in range(octaves):
        f = 2.0**o
        total += amp * value_noise2(x * f, y * f, seed=seed + 101 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.power(np.clip(c, 0, 1), 2.2)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    return np.power(np.clip(c, 0, 1), 1 / 2.2)


BACKGROUNDS = ("drape_green", "drape_blue", "steel_table", "wood", "foam_grey")
BACKGROUND_TEXTURE_M = 2.0  # metres covered by one background texture tile


def tile_noise(rng: np.random.Generator, size: int, cells: int | tuple[int, int]) -> np.ndarray:
    """Tileable smooth noise in [0, 1], (size, size): a random cells grid upsampled bicubically with wrap-around."""
    cy, cx = (cells, cells) if isinstance(cells, int) else cells
    grid = rng.random((cy, cx)).astype(np.float32)
    pad = 3
    big = np.pad(grid, pad, mode="wrap")
    sy, sx = size / cy, size / cx
    up = cv2.resize(big, (int(round(big.shape[1] * sx)), int(round(big.shape[0] * sy))), interpolation=cv2.INTER_CUBIC)
    oy, ox = int(round(pad * sy)), int(round(pad * sx))
    return np.clip(up[oy : oy + size, ox : ox + size], 0, 1)


def tile_fbm(rng: np.random.Generator, size: int, cells: int, octaves: int = 4) -> np.ndarray:
    total, amp, norm = np.zeros((size, size), np.float32), 1.0, 0.0
    for o in range(octaves):
        total += amp * tile_noise(rng, size, min(size // 2, cells * 2**o))
        norm += amp
        amp *= 0.5
    return total / norm


def background_texture(kind: str, rng: np.random.Generator, size: int = 1024) -> np.ndarray:
    """A tileable (size, size, 3) linear-albedo image covering BACKGROUND_TEXTURE_M metres square."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    low = tile_fbm(rng, size, 6, 4)
    fine = tile_noise(rng, size, size // 2)
    if kind.startswith("drape"):
        base = np.array([0.16, 0.42, 0.36]) if kind == "drape_green" else np.array([0.20, 0.36, 0.58])
        warp = tile_fbm(rng, size, 3, 3)
        folds = 0.5 + 0.5 * np.sin(2 * np.pi * (4 * xx + 2.0 * warp + 0.6 * low))
        weave = tile_noise(rng, size, (size // 2, size // 8))
        shade = 0.72 + 0.22 * folds + 0.10 * (low - 0.5) + 0.05 * (weave - 0.5) + 0.06 * (fine - 0.5)
        img = base[None, None, :] * shade[..., None]
    elif kind == "steel_table":
        streak = tile_noise(rng, size, (size // 2, 4))
        shade = 0.55 + 0.12 * (low - 0.5) + 0.10 * (streak - 0.5) + 0.05 * (fine - 0.5)
        img = np.array([0.60, 0.61, 0.63])[None, None, :] * shade[..., None] * 1.1
    elif kind == "wood":
        warp = tile_fbm(rng, size, 4, 3)
        rings = 0.5 + 0.5 * np.sin(2 * np.pi * (60 * yy + 3 * warp) + 2 * fine)
        shade = 0.75 + 0.2 * rings + 0.1 * (low - 0.5)
        img = np.array([0.55, 0.36, 0.21])[None, None, :] * shade[..., None]
    else:
        pores = (tile_noise(rng, size, size // 2) > 0.85) * 0.2
        shade = 0.8 + 0.1 * (low - 0.5) + 0.1 * (fine - 0.5) - pores
        img = np.array([0.42, 0.43, 0.45])[None, None, :] * shade[..., None]
    # a few printed labels, tape and swabs so the scene is not featureless
    for _ in range(int(rng.integers(5, 10))):
        cx, cy = rng.uniform(0, size, 2)
        w, h = rng.uniform(0.006, 0.03, 2) * size
        ang = rng.uniform(0, 180)
        col = rng.choice([0.85, 0.12, 0.5]) * np.ones(3) + rng.uniform(-0.08, 0.08, 3)
        box = cv2.boxPoints(((cx, cy), (w, h), ang)).astype(np.int32)
        mask = np.zeros((size, size), np.uint8)
        cv2.fillPoly(mask, [box], 1)
        mask = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), 0.8)[..., None]
        img = mask * (0.75 * col + 0.25 * img) + (1 - mask) * img
    return srgb_to_linear(np.clip(img, 0, 1)).astype(np.float32)


def sample_texture(tex: np.ndarray, s: np.ndarray, t: np.ndarray, tile_m: float = BACKGROUND_TEXTURE_M) -> np.ndarray:
    """Bilinear lookup of a tiled texture at plane coordinates (s, t) in metres; returns (N, 3)."""
    n = tex.shape[0]
    count = s.size
    cols = 1024
    rows = max(1, -(-count // cols))
    pad = rows * cols - count
    mx = np.pad(np.mod(s / tile_m * n, n).ravel(), (0, pad)).astype(np.float32).reshape(rows, cols)
    my = np.pad(np.mod(t / tile_m * n, n).ravel(), (0, pad)).astype(np.float32).reshape(rows, cols)
    out = cv2.remap(tex, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, 3)[:count]
