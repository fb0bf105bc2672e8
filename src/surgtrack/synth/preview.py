"""A contact sheet per sequence (SEQ/preview.png): RGB, mask overlay and colourised depth for a few frames."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..io import read_depth, read_mask, read_rgb


def colourise_depth(depth_m: np.ndarray, near: float = 0.2, far: float = 1.4) -> np.ndarray:
    """Turbo colour map of depth in metres (RGB uint8); invalid pixels black."""
    x = np.clip((depth_m - near) / (far - near), 0, 1)
    img = cv2.applyColorMap((255 - x * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    img[depth_m <= 0] = 0
    return img


def overlay_mask(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Tint the mask green and outline it."""
    out = rgb.astype(np.float32)
    out[mask] = 0.55 * out[mask] + 0.45 * np.array([40, 255, 80])
    out = out.astype(np.uint8)
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, (255, 255, 0), 1)
    return out


def write_preview(seq: Path | str, n_frames: int = 4, tile_width: int = 320, extra: tuple[int, ...] = ()) -> Path:
    """Write SEQ/preview.png from the frames on disk (evenly spaced, plus the `extra` frame indices)."""
    seq = Path(seq)
    frames = sorted((seq / "rgb").glob("*.png"))
    idx = {int(round(k)) for k in np.linspace(0, len(frames) - 1, min(n_frames, len(frames)))}
    idx |= {i for i in extra if 0 <= i < len(frames)}
    picks = [frames[i] for i in sorted(idx)]
    rows = []
    for p in picks:
        rgb = read_rgb(p)
        depth = read_depth(seq / "depth" / p.name, 0.001)
        mp = seq / "masks" / p.name
        mask = read_mask(mp) if mp.exists() else np.zeros(depth.shape, bool)
        valid = (depth[mask] > 0).mean() if mask.any() else 0.0
        tiles = [rgb, overlay_mask(rgb, mask), colourise_depth(depth)]
        scale = tile_width / rgb.shape[1]
        size = (tile_width, int(round(rgb.shape[0] * scale)))
        tiles = [cv2.resize(t, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST) for t in tiles]
        label = f"frame {p.stem}  mask {int(mask.sum())} px  depth valid {100 * valid:.0f}%"
        cv2.putText(tiles[1], label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
        rows.append(np.concatenate(tiles, 1))
    sheet = np.concatenate(rows, 0)
    out = seq / "preview.png"
    cv2.imwrite(str(out), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR))
    return out
