"""Each sequence's pose errors split along its shaft: the turn about the shaft, the slide along it, and the rest.

    .venv/bin/python benchmarks/shaft_errors.py RESULTS DATA

RESULTS holds one result folder a sequence (OUT/ob_in_cam/), e.g. ``bench_out/surgtrack``; DATA the rendered
sequences of the same names, e.g. ``bench_out/data``. The poses are aligned at the first frame as `surgtrack eval`
aligns them; the shaft is the rendered instrument's own axis line (below), else the first principal axis of the
evaluation's model points (the surface the video shows) through their centroid. For each frame, E = gt^-1 pose maps
the model as tracked onto the model as it is: the turn is the twist of E's rotation about the shaft, the slide the
part of the points' centroid displacement along it. Printed: the median and the 90th percentile over the frames, and
the ADD and ADD-S AUC (lost frames counted as `surgtrack eval` counts them) as tracked, with the turn taken out of
every pose, with the slide taken out, and with both: what each costs.

A sequence rendered by `surgtrack synth` names its instrument in synth.json; its shaft is then the instrument's own
axis line (through the tip), not the principal axis through the centroid. The two differ where the model carries
parts off the shaft (a thoracoscope's light post): a turn taken out about a line beside the shaft leaves a shift
behind, and what the turn costs is then underestimated.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from result_runs import result_runs
from scipy.spatial.transform import Rotation

from surgtrack.geometry import inv_T, make_T, so3_exp
from surgtrack.io import Sequence
from surgtrack.metrics import add_errors, adds_errors, align_first_frame, alignment_anchor, auc, model_points
from surgtrack.synth.instruments import Instrument, load_instrument


def shaft_of(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The shaft of a model's points (object frame): their centroid and first principal axis."""
    centre = pts.mean(axis=0)
    return centre, np.linalg.svd(pts - centre, full_matrices=False)[2][0]


def rendered_instrument(root: Path) -> Instrument | None:
    """The instrument a sequence folder's synth.json names (object frame = the ground truth's), or None when the
    folder was not rendered by `surgtrack synth` or the instrument's mesh is not at hand."""
    try:
        return load_instrument(json.loads((root / "synth.json").read_text())["spec"]["instrument"])
    except (OSError, KeyError, ValueError):
        return None


def turn_about(axis: np.ndarray, on_line: np.ndarray, angle: float) -> np.ndarray:
    """4x4 turn by ``angle`` (radians) about the line through ``on_line`` along the unit ``axis``."""
    R = so3_exp(angle * axis)
    return make_T(R, on_line - R @ on_line)


def sequence_shaft(seq: Sequence) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A sequence's evaluation model points (object frame, as `surgtrack eval` scores them), their centroid, the
    shaft's direction and a point on its line: the rendered instrument's own axis and tip when synth.json names
    one, else the points' first principal axis through their centroid."""
    pts = model_points(seq.gt_visible_points(), seq.gt_model())
    centre, axis = shaft_of(pts)
    instrument = rendered_instrument(seq.root)
    if instrument is None:
        return pts, centre, axis, centre
    return pts, centre, instrument.axis, instrument.tip


def aligned_run(seq: Sequence, gt: dict[str, np.ndarray],
                est: dict[str, np.ndarray]) -> tuple[list[str], dict[str, np.ndarray]]:
    """The frame ids with ground truth and the tracked poses aligned at the first frame as `surgtrack eval` aligns
    them."""
    ids = [i for i in seq.ids if i in gt]
    anchor = alignment_anchor(est, gt, ids)
    return ids, align_first_frame(est, est[anchor], gt[anchor])


def shaft_parts(E: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> tuple[float, float, float]:
    """An error E = gt^-1 pose split along the shaft: the twist of its rotation about the axis (radians, signed),
    the centroid's displacement along the axis (m, signed) and across it (m)."""
    q = Rotation.from_matrix(E[:3, :3]).as_quat()  # x, y, z, w
    q = -q if q[3] < 0 else q
    d = E[:3, :3] @ centre + E[:3, 3] - centre
    along = float(d @ axis)
    return 2 * float(np.arctan2(q[:3] @ axis, q[3])), along, float(np.linalg.norm(d - along * axis))


def without(E: np.ndarray, centre: np.ndarray, axis: np.ndarray, on_line: np.ndarray, turn: bool,
            slide: bool) -> np.ndarray:
    """The error E with its twist about the shaft (the axis line through ``on_line``) and/or its slide along it (of
    ``centre``) removed."""
    if turn:
        E = E @ inv_T(turn_about(axis, on_line, shaft_parts(E, centre, axis)[0]))
    if slide:
        E = E.copy()
        E[:3, 3] -= shaft_parts(E, centre, axis)[1] * axis
    return E


def main() -> None:
    totals = []
    for out, seq, gt, est in result_runs(__doc__.splitlines()[0], "ob_in_cam"):
        ids, aligned = aligned_run(seq, gt, est)
        pts, centre, axis, on_line = sequence_shaft(seq)
        turn, slide, rest = [], [], []
        for i in ids:
            if i in aligned:
                t, along, across = shaft_parts(inv_T(gt[i]) @ aligned[i], centre, axis)
                turn.append(abs(np.degrees(t)))
                slide.append(abs(along) * 100)
                rest.append(across * 100)

        def stat(x: list[float]) -> str:
            return f"{np.median(x):5.1f} / {np.percentile(x, 90):5.1f}"

        G = [gt[i] for i in ids]
        aucs = []
        for errors in (add_errors, adds_errors):
            for t, s in ((False, False), (True, False), (False, True), (True, True)):
                poses = [None if i not in aligned else gt[i] @ without(inv_T(gt[i]) @ aligned[i], centre, axis,
                                                                       on_line, t, s) for i in ids]
                aucs.append(auc(errors(poses, G, pts)))
        totals.append(aucs)
        add, add_s = (" / ".join(f"{a:5.2f}" for a in part) for part in (aucs[:4], aucs[4:]))
        print(f"{out.name:18} turn {stat(turn)} deg   slide {stat(slide)} cm   across {stat(rest)} cm   "
              f"ADD AUC {add}   ADD-S AUC {add_s}")
    mean = np.mean(totals, axis=0)
    print(f"{'mean':18} AUC as tracked / without the turn / without the slide / without both: "
          f"ADD {' / '.join(f'{a:5.2f}' for a in mean[:4])}, ADD-S {' / '.join(f'{a:5.2f}' for a in mean[4:])}")


if __name__ == "__main__":
    main()
