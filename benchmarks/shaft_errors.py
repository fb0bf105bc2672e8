"""Each sequence's pose errors split along its shaft: the turn about the shaft, the slide along it, and the rest.

    .venv/bin/python benchmarks/shaft_errors.py RESULTS DATA

RESULTS holds one result folder a sequence (OUT/ob_in_cam/), e.g. ``bench_out/surgtrack``; DATA the rendered
sequences of the same names, e.g. ``bench_out/data``. The poses are aligned at the first frame as `surgtrack eval`
aligns them; the shaft is the first principal axis of the evaluation's model points (the surface the video shows).
For each frame, E = gt^-1 pose maps the model as tracked onto the model as it is: the turn is the twist of E's
rotation about the shaft, the slide the part of the points' centroid displacement along it. Printed: the median and
the 90th percentile over the frames.
"""

from __future__ import annotations

import numpy as np
from result_runs import result_runs
from scipy.spatial.transform import Rotation

from surgtrack.geometry import inv_T
from surgtrack.metrics import align_first_frame, alignment_anchor, model_points


def main() -> None:
    for out, seq, gt, est in result_runs(__doc__.splitlines()[0], "ob_in_cam"):
        ids = [i for i in seq.ids if i in gt and i in est]
        anchor = alignment_anchor(est, gt, ids)
        aligned = align_first_frame(est, est[anchor], gt[anchor])
        pts = model_points(seq.gt_visible_points(), seq.gt_model())
        centre = pts.mean(axis=0)
        axis = np.linalg.svd(pts - centre, full_matrices=False)[2][0]
        turn, slide, rest = [], [], []
        for i in ids:
            if i not in aligned:
                continue
            E = inv_T(gt[i]) @ aligned[i]
            q = Rotation.from_matrix(E[:3, :3]).as_quat()  # x, y, z, w
            turn.append(np.degrees(2 * np.arctan2(abs(q[:3] @ axis), abs(q[3]))))
            d = E[:3, :3] @ centre + E[:3, 3] - centre
            slide.append(abs(d @ axis) * 100)
            rest.append(np.linalg.norm(d - (d @ axis) * axis) * 100)

        def stat(x: list[float]) -> str:
            return f"{np.median(x):5.1f} / {np.percentile(x, 90):5.1f}"

        print(f"{out.name:18} turn {stat(turn)} deg   slide {stat(slide)} cm   across {stat(rest)} cm")


if __name__ == "__main__":
    main()
