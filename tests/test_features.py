"""Keypoints on the instrument region (input of eq. 5): every detector finds them inside the mask only, and
matches between two views give the image motion between them."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from surgtrack.config import PreprocessConfig
from surgtrack.features import FeatureExtractor, match
from surgtrack.io import Frame
from surgtrack.preprocess import preprocess, remasked

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


class _Counting:
    """An OpenCV detector that counts its detections."""

    def __init__(self, detector) -> None:
        self.detector, self.calls = detector, 0

    def detectAndCompute(self, image, mask):  # noqa: N802 - OpenCV's name
        self.calls += 1
        return self.detector.detectAndCompute(image, mask)


@pytest.mark.parametrize("kind", ["sift", "orb", "xfeat"])
def test_a_frame_masked_again_in_its_crop_gets_what_a_fresh_detection_gives(kind: str):
    """The tracker masks a frame again at its tracked pose (`preprocess.remasked`): in the same crop XFeat takes the
    keypoints it found in the crop, SIFT those it found on the first mask when the second lies within it; ORB, and
    SIFT on a mask that reaches beyond the first, detect again. Each result is that of a fresh detection."""
    mask = np.zeros((H, W), bool)
    mask[70:170, 90:230] = True
    mask[100:140, 120:200] = False
    within, beyond = mask.copy(), mask.copy()
    within[80:160, 100:120] = False  # the same box, a mask within the first
    beyond[100:140, 120:200] = True  # the same box, a mask beyond the first
    obs = observation(0, mask)
    extract = FeatureExtractor(kind, max_keypoints=400)
    if kind != "xfeat":
        extract._cv = _Counting(extract._cv)
    first = extract(obs)
    for second, detections in ((within, {"sift": 1, "orb": 2}), (beyond, {"sift": 2, "orb": 3})):
        again = remasked(obs, second, PreprocessConfig())
        f, fresh = extract(again), FeatureExtractor(kind, max_keypoints=400)(again)
        assert len(f) > 0 and len(f) != len(first)
        for name in ("uv", "desc", "xyz", "normals"):
            assert np.array_equal(getattr(f, name), getattr(fresh, name)), name
        if kind != "xfeat":
            assert extract._cv.calls == detections[kind]
    if kind == "sift":
        calls = extract._cv.calls
        extract(observation(6, mask))  # another frame: detected anew
        assert extract._cv.calls == calls + 1


def test_sift_keypoints_on_the_mask_are_those_of_a_masked_detection():
    """SIFT ranks its keypoints over the whole crop and only then applies a mask, so detecting on the crop and keeping
    the keypoints on the mask gives OpenCV's masked detection (keypoints, order, descriptors)."""
    mask = np.zeros((H, W), bool)
    mask[70:170, 90:230] = True
    mask[100:140, 120:200] = False
    obs = observation(0, mask)
    f = FeatureExtractor("sift", max_keypoints=60)(obs)  # fewer than the crop holds: the ranking matters
    rs, cs = 62, 82  # the extractor's crop: the mask's box grown by 8 pixels
    image = cv2.cvtColor(obs.frame.rgb[rs:178, cs:238], cv2.COLOR_RGB2GRAY)
    scale = 320 / 156
    image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    on = cv2.dilate(mask[rs:178, cs:238].astype(np.uint8), np.ones((5, 5), np.uint8))
    on = cv2.resize(on, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_NEAREST)
    kps, desc = cv2.SIFT_create(nfeatures=60, contrastThreshold=0.02).detectAndCompute(image, on)
    uv = (np.array([k.pt for k in kps], np.float32) + 0.5) / scale - 0.5 + np.array([cs, rs], np.float32)
    u, v = np.round(uv).astype(int).T
    kept = obs.at(v, u)[0]  # those with trusted depth
    assert len(f) == kept.sum() > 10
    assert np.array_equal(f.uv, uv[kept]) and np.array_equal(f.desc, desc[kept])
