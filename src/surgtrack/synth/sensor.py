"""Intel RealSense D4xx sensor model: what an active-stereo depth camera and its colour imager do to a clean render.

Depth (the reference is the left imager, the right imager sits BASELINE metres along +x):
- noise from disparity error: sigma_z = SUBPIXEL_RMS * z^2 / (F_IR * BASELINE), spatially correlated, clipped at
  NOISE_CLIP sigma; 1 mm quantisation happens when the depth PNG is written (uint16 millimetres);
- dropouts: at grazing angles, on IR specular highlights of metal (the emitter sits beside the imagers, so a
  shaft's centre line facing the camera saturates), on saturated colour highlights, on IR-dark materials;
- stereo shadow: surface points hidden from the right imager, or outside its view (the invalid band on the left of
  the image and beside near objects, on their left);
- flying pixels and thin-structure loss at depth discontinuities, small holes, range limits.
Colour: optical blur, vignetting, a soft tone curve, signal-dependent noise, optional motion blur.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.special import ndtr

BASELINE = 0.05  # m, D435 stereo baseline
F_IR = 383.0  # px, IR focal length of a D435 at 640x480
SUBPIXEL_RMS = 0.08  # px, disparity noise
NOISE_CLIP = 3.0  # depth noise is clipped at this many sigma
MIN_Z, MAX_Z = 0.16, 3.0  # m, valid depth range
QUANT = 0.001  # m, depth PNG unit


def depth_sigma(z: np.ndarray | float) -> np.ndarray:
    """Standard deviation of depth noise (m) at depth z (m)."""
    return SUBPIXEL_RMS * np.asarray(z, dtype=np.float64) ** 2 / (F_IR * BASELINE) + 0.0002


def depth_error_bound(z: np.ndarray | float) -> np.ndarray:
    """Largest |measured - true| depth error at an interior (non-edge) pixel, quantisation included."""
    return NOISE_CLIP * depth_sigma(z) + 0.5 * QUANT + 1e-6


@dataclass
class DepthInputs:
    """Per-pixel quantities the depth model needs; (H, W) arrays."""

    z: np.ndarray  # true z-depth, metres, 0 where nothing is hit
    cos_view: np.ndarray  # |normal . view direction|
    ir_dropout: np.ndarray  # material base dropout probability
    ir_specular: np.ndarray  # strength of the emitter's specular reflection, [0, 1]
    saturated: np.ndarray  # bool: a strong specular highlight on metal (saturates the IR imagers too)
    stereo_shadow: np.ndarray  # bool: hidden from the right imager or outside its view


def _smooth_normal(rng: np.random.Generator, shape: tuple[int, int], sigma: float) -> np.ndarray:
    """Spatially correlated standard-normal field (unit variance) with Gaussian correlation length sigma px."""
    g = rng.standard_normal(shape).astype(np.float32)
    if sigma > 0.3:
        g = cv2.GaussianBlur(g, (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        g /= max(float(g.std()), 1e-6)
    return g


def realsense_depth(inp: DepthInputs, rng: np.random.Generator, px_scale: float) -> np.ndarray:
    """Measured depth (H, W) float32 metres, 0 = invalid. px_scale = image width / 640 (feature sizes scale)."""
    z = inp.z.astype(np.float64)
    shape = z.shape
    valid = (z > MIN_Z) & (z < MAX_Z)
    # correlated disparity noise
    g = 0.6 * rng.standard_normal(shape) + 0.8 * _smooth_normal(rng, shape, 1.5 * px_scale)
    noisy = z + depth_sigma(z) * np.clip(g, -NOISE_CLIP, NOISE_CLIP)
    # dropout probability from the surface, thresholded with a blobby uniform field
    p_graze = np.clip((0.3 - inp.cos_view) / 0.2, 0, 1)
    p_spec = 0.75 * np.clip((inp.ir_specular - 0.5) / 0.4, 0, 1)
    p_sat = np.where(inp.saturated, 0.5, 0.0)
    keep = (1 - p_graze) * (1 - p_spec) * (1 - p_sat) * (1 - inp.ir_dropout)
    u = ndtr(_smooth_normal(rng, shape, 1.2 * px_scale))
    drop = u > keep
    holes = ndtr(_smooth_normal(rng, shape, 6.0 * px_scale)) < 0.0015
    drop |= holes | inp.stereo_shadow
    # depth discontinuities: the matcher's window loses thin near structure and mixes depths
    big = np.where(z > 0, z, 1e3).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    zmin = cv2.erode(big, kernel, borderType=cv2.BORDER_REPLICATE)
    zmax = cv2.dilate(np.where(z > 0, z, 0).astype(np.float32), kernel, borderType=cv2.BORDER_REPLICATE)
    edge = valid & (zmax - zmin > 0.015) & (zmin < 1e2)
    fg_edge = edge & (z - zmin < 0.005)
    r = rng.uniform(size=shape)
    drop |= fg_edge & (r < 0.35)
    fly = edge & ~drop & (rng.uniform(size=shape) < 0.3)
    alpha = rng.uniform(0.15, 0.85, size=shape)
    noisy = np.where(fly, zmin + alpha * (np.minimum(zmax, MAX_Z) - zmin), noisy)
    out = np.where(valid & ~drop, noisy, 0.0)
    return out.astype(np.float32)


def tone_map(linear: np.ndarray) -> np.ndarray:
    """Linear radiance to display [0, 1]: a soft shoulder (auto-exposed camera) and sRGB-like gamma."""
    x = np.maximum(linear, 0)
    shoulder = np.where(x < 0.8, x, 0.8 + 0.2 * (1 - np.exp(-(x - 0.8) / 0.2)))
    return np.power(np.clip(shoulder, 0, 1), 1 / 2.2)


def realsense_rgb(display: np.ndarray, rng: np.random.Generator, px_scale: float, noise: bool) -> np.ndarray:
    """Display-referred float image (H, W, 3) to the 8-bit colour frame: optics blur, vignetting, sensor noise."""
    h, w = display.shape[:2]
    img = cv2.GaussianBlur(display.astype(np.float32), (0, 0), 0.55 * max(px_scale, 0.5))
    if noise:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (w / 2)) ** 2
        img = img * (1 - 0.18 * r2)[..., None]
        sigma = np.sqrt(0.00004 + 0.0004 * img)
        lum = rng.standard_normal((h, w, 1)).astype(np.float32)
        chroma = rng.standard_normal((h, w, 3)).astype(np.float32)
        img = img + sigma * (0.8 * lum + 0.45 * chroma)
    return np.clip(np.round(img * 255), 0, 255).astype(np.uint8)


def motion_blur(img: np.ndarray, weight: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Blur along the image motion (dx, dy) pixels where weight (H, W) in [0, 1] is high."""
    length = float(np.hypot(dx, dy))
    if length < 1.0:
        return img
    n = int(np.ceil(length)) | 1
    k = np.zeros((n, n), np.float32)
    c = n // 2
    for s in np.linspace(-0.5, 0.5, 2 * n):
        k[int(round(c + s * dy)), int(round(c + s * dx))] += 1
    k /= k.sum()
    blurred = cv2.filter2D(img, -1, k, borderType=cv2.BORDER_REFLECT)
    return img * (1 - weight[..., None]) + blurred * weight[..., None]
