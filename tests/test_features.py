"""Keypoints on the instrument region (input of eq. 5): every detector finds them inside the mask only, and
matches between two views give the image motion between them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surgtrack.config import PreprocessConfig
from surgtrack.features import FeatureExtractor, match
from surgtrack.io import Frame
from surgtrack.preprocess import preprocess

K = np.array([[300.0, 0.0, 160.0], [0.0, 300.0, 120.0], [0.0, 0.0, 1.0]])
H, W = 240, 320


def texture(seed: int = 3) -> np.ndarray:
    """A blotchy colour texture, wider than the image so that it can be shifted."""
    noise = np.random.default_rng(seed).random((H, W + 40, 3)).astype(np.float32)
    return (255 * cv2.normalize(cv2.GaussianBlur(noise, (0, 0), 2.0), None, 0, 1, cv2.NORM_MINMAX)).astype(np.uint8)


def observation(shift: int, mask: np.ndarray):
    """The texture moved ``shift`` pixels to the right, on a plane 0.4 m away, the mask moved with it."""
    rgb = np.ascontiguousarray(texture()[:, 20 - shift: 20 - shift + W])
    depth = np.full((H, W), 0.4, np.float32)
    frame = Frame(0, "0", rgb, depth, K, np.roll(mask, shift, axis=1))
    return preprocess(frame, frame.mask, PreprocessConfig())


@pytest.mark.parametrize("kind", ["sift", "orb", "xfeat"])
def test_matches_give_the_image_motion_and_keypoints_stay_on_the_mask(kind: str):
    mask = np.zeros((H, W), bool)
    mask[70:170, 90:230] = True
    extract = FeatureExtractor(kind, max_keypoints=400)
    a, b = observation(0, mask), observation(6, mask)
    fa, fb = extract(a), extract(b)
    assert len(fa) >= 20 and len(fb) >= 20
    grown = cv2.dilate(mask.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    u, v = np.round(fa.uv).astype(int).T
    assert grown[v, u].all()
    ia, ib = match(fa, fb, extract.norm, 0.8)
    assert len(ia) >= 10
    motion = fb.uv[ib] - fa.uv[ia]
    assert np.median(np.abs(motion - [6.0, 0.0]).max(axis=1)) < 1.0
    assert np.allclose(fa.xyz[:, 2], 0.4, atol=1e-3)


@pytest.mark.parametrize("kind", ["sift", "xfeat"])
def test_a_thin_instrument_crop_gets_keypoints(kind: str):
    """A shaft a few pixels wide: its crop is narrower than XFeat's 32-pixel stride."""
    mask = np.zeros((H, W), bool)
    mask[118:124, 10:310] = True
    f = FeatureExtractor(kind)(observation(0, mask))
    assert len(f) > 0
    assert (np.abs(f.uv[:, 1] - 120.5) < 8).all()
