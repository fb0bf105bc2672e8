"""Each re-localisation of a tracked run against the ground truth: how far the instrument really moved while lost,
and how far the re-localised pose lies from the last tracked one (both for the tracker's object origin); without
masks also its made mask's colour and that colour's share of the median of the last tracked frames' (what
``failure.relocalise_colour`` holds a re-localisation to).

    .venv/bin/python benchmarks/relocalisations.py RESULTS DATA

RESULTS holds one result folder a sequence (OUT/track.jsonl, OUT/ob_in_cam/), e.g. ``bench_out/surgtrack``;
DATA the rendered sequences of the same names, e.g. ``bench_out/data``.
"""

from __future__ import annotations

import numpy as np
from result_runs import result_runs

from surgtrack.io import read_track_log
from surgtrack.tracker import COLOURS_KEPT


def main() -> None:
    for out, _, gt, est in result_runs(__doc__.splitlines()[0], "track.jsonl"):
        status = read_track_log(out)
        ids = [s["frame"] for s in status]
        origin = np.linalg.inv(gt[ids[0]]) @ np.r_[est[ids[0]][:3, 3], 1]  # the tracker's origin, object frame
        last, colours = None, []
        for i, s in enumerate(status):
            if s["status"] == "relocalised" and last is not None:
                prev, cur = ids[last], ids[i]
                true_move = np.linalg.norm((gt[cur] @ origin)[:3] - (gt[prev] @ origin)[:3])
                est_move = np.linalg.norm(est[cur][:3, 3] - est[prev][:3, 3])
                error = np.linalg.norm(est[cur][:3, 3] - (gt[cur] @ origin)[:3])
                colour = ""
                if s.get("colour") is not None and colours:
                    share = s["colour"] / np.median(colours[-COLOURS_KEPT:])
                    colour = f"  colour {s['colour']:.2f}, {share:.2f} of before"
                print(f"{out.name:<18} lost {last}->{i} ({i - last:3d} frames)  moved: true {100 * true_move:5.1f} "
                      f"cm, re-localised {100 * est_move:5.1f} cm  origin error {100 * error:5.1f} cm{colour}")
            if s["status"] != "lost":
                last = i
            if s["status"] == "tracked" and s.get("colour") is not None:
                colours.append(s["colour"])


if __name__ == "__main__":
    main()
