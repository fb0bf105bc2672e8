"""How far a rendered instrument's own markings show its turn about the shaft, with everything else known.

    .venv/bin/python benchmarks/marking_turn.py DATA [--every N]

DATA holds sequences that `surgtrack synth` rendered (synth.json names the instrument). For every N-th frame the
instrument's marking points (surface points whose albedo differs from their material's by more than 0.3: bands, tick
marks, lettering) are placed at the true pose turned by -60 to +60 degrees about the instrument's own axis, and the
frame's mean grey level under those that face the camera (on the true mask, depth within 6 mm) is taken, less that
under the unmarked points of the same materials: the markings' contrast at that turn. A turn the markings show
makes the contrast fall off on both sides of the truth. Printed per sequence: the frames with at least 20 marking
points in view, and over them the median turn range (degrees) in which the contrast stays within 10 % of its value
at the truth, and the share of those frames where that range reaches the end of the search on one side or both
(the markings bound the turn one way only, or not at all).

Oracle figures: the true pose, the true mask and the true marking geometry, none of which a tracker has.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
import trimesh
from shaft_errors import rendered_instrument, turn_about

from surgtrack.geometry import project, transform
from surgtrack.io import Frame, open_sequence
from surgtrack.synth.instruments import Instrument

TURNS = np.radians(np.arange(-60, 61, 5))
TRUTH = len(TURNS) // 2  # the index of no turn
KEEP = 0.9  # share of the truth's contrast within which a turn counts as not told apart


def marking_points(inst: Instrument, n: int = 300_000) -> tuple[np.ndarray, np.ndarray]:
    """Object-frame surface points of the instrument's markings, and unmarked points of the marked materials."""
    pts, faces = trimesh.sample.sample_surface(inst.mesh, n, seed=0)
    albedo = inst.albedo(pts, faces)
    base = np.array([m.albedo for m in inst.materials])[inst.face_material[faces]]
    marked_material = np.array([m.marked for m in inst.materials])[inst.face_material[faces]]
    mark = np.abs(albedo - base).max(axis=1) > 0.3
    return pts[mark], pts[marked_material & ~mark]


def off_axis(inst: Instrument, pts: np.ndarray) -> np.ndarray:
    """Each point's direction away from the instrument's axis (object frame): the way a shaft's surface faces."""
    d = pts - inst.tip
    return d - np.outer(d @ inst.axis, inst.axis)


def grey_under(frame: Frame, grey: np.ndarray, pose: np.ndarray, pts: np.ndarray,
               radial: np.ndarray) -> tuple[float, int]:
    """Mean grey level under the points (object frame, facing ``radial``) that face the camera at ``pose`` and land
    on the true mask at their own depth, and how many do."""
    cam = transform(pose, pts)
    uv, z = project(cam, frame.K)
    facing = np.einsum("ij,ij->i", radial @ pose[:3, :3].T, -cam) > 0
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    h, w = grey.shape
    ok = facing & (u >= 0) & (u < w) & (v >= 0) & (v < h) & (z > 0)
    ok[ok] &= (frame.mask[v[ok], u[ok]] > 0) & (np.abs(frame.depth[v[ok], u[ok]] - z[ok]) < 0.006)
    n = int(ok.sum())
    return (float(grey[v[ok], u[ok]].mean()) if n else np.nan), n


def untold_range(contrast: np.ndarray) -> tuple[float, bool]:
    """The contiguous turn range (degrees) about the truth where the contrast stays within KEEP of the truth's, and
    whether it reaches an end of the search."""
    near = np.sign(contrast[TRUTH]) * contrast >= KEEP * abs(contrast[TRUTH])
    lo = hi = TRUTH
    while lo > 0 and near[lo - 1]:
        lo -= 1
    while hi < len(TURNS) - 1 and near[hi + 1]:
        hi += 1
    return float(np.degrees(TURNS[hi] - TURNS[lo])), lo == 0 or hi == len(TURNS) - 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", type=Path)
    ap.add_argument("--every", type=int, default=10)
    a = ap.parse_args()
    print("| sequence | frames with markings in view | median turn range not told apart, degrees | "
          "range open on a side |")
    print("|---|---|---|---|")
    for root in sorted(a.data.iterdir()):
        inst = rendered_instrument(root)
        if inst is None:
            continue
        sets = [(pts, off_axis(inst, pts)) for pts in marking_points(inst)]  # marked, then unmarked
        turns = [turn_about(inst.axis, inst.tip, t) for t in TURNS]
        seq = open_sequence(root)
        gt = seq.gt_poses()
        ranges, open_sided = [], 0
        for i in range(0, len(seq), a.every):
            frame = seq[i]
            if frame.mask is None or frame.id not in gt:
                continue
            grey = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
            marked, plain = ([grey_under(frame, grey, gt[frame.id] @ T, pts, radial) for T in turns]
                             for pts, radial in sets)
            contrast = np.array([m - p for (m, _), (p, _) in zip(marked, plain, strict=True)])
            if marked[TRUTH][1] < 20 or not np.isfinite(contrast[TRUTH]):
                continue
            width, reaches_end = untold_range(np.nan_to_num(contrast, nan=0.0))
            ranges.append(width)
            open_sided += reaches_end
        n = len(ranges)
        print(f"| {root.name} | {n} | {np.median(ranges) if n else float('nan'):.0f} | "
              f"{100 * open_sided / n if n else float('nan'):.0f} % |")


if __name__ == "__main__":
    main()
