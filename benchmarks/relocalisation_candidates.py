"""Where re-localisation fails: is a right pose among the candidates a lost frame refines, and if so, what refuses it?

    .venv/bin/python benchmarks/relocalisation_candidates.py DATA OUT [--first-mask-only] [--config C.json]
                                                               [--right 0.03] [--only SEQ,SEQ]

Each sequence of DATA is tracked as `surgtrack track` tracks it (into OUT/SEQ), while every candidate pose a lost
frame's re-localisation refines (`SurgTracker._refined`) is kept with its appearance score, and the winner of
each candidate set (`_best_candidate`; without masks one set a colour region). Each set is also refined once from
the true pose (the run's random draws kept as they were): whether the frame and the model would hold the truth
had a candidate started there. Against the ground truth (ADD over the evaluation's model points, the run's first
pose aligned as `surgtrack eval` aligns it) a pose is right when its ADD is below ``--right`` (3 cm). Each frame
on which re-localisation ran counts once, in the first class that fits it:

- taken right: the frame came out re-localised, its pose right;
- right there: it came out re-localised, wrong, while a right candidate had been refined;
- taken wrong: it came out re-localised, wrong, no candidate right;
- lost after: a right winner was taken, then lost by the checks that follow (`unsure`, `seen past`);
- silhouette: a right candidate won its set, and the frame stayed lost all the same: its silhouette agreement with
  its region fell below ``failure.relocalise_min_iou``, or, without masks, its made mask's colour below
  ``failure.relocalise_colour`` of the colour before the loss (`SurgTracker._looks_like_before`);
- beaten: a right candidate was refined and kept, and a wrong one won its set (fit, then appearance, then motion);
- appearance: a right candidate was refined and dropped by the appearance check (``failure.relocalise_min_ncc``);
- refined off: a candidate started right, and refinement moved it off or the reach or fit bound dropped it;
- none right: no candidate started right.

``truth held`` counts the frames of ``taken wrong`` and ``none right`` on which the true pose, refined, stayed
right and within the bounds (the candidates missed a pose the frame and the model support), and ``on it`` those
on which at least half of a set's pixels (the given mask, or without masks the colour region) lie on the true
mask (the search looked at the instrument).

Printed: one row a sequence, then the sums. The default configuration is the SDF off, whose poses do not depend
on timing (the runs are then `surgtrack bench`'s, pose file for pose file).
"""

from __future__ import annotations

from collections import Counter

import numpy as np
from result_runs import sequence_names, tracker_config, tracking_parser

from surgtrack.io import open_sequence, read_poses, read_track_log
from surgtrack.metrics import add_errors, model_points
from surgtrack.pipeline import track_sequence
from surgtrack.tracker import SurgTracker

CLASSES = ("taken right", "right there", "taken wrong", "lost after", "silhouette", "beaten", "appearance",
           "refined off", "none right")
ALSO = ("truth held", "on it")  # counted beside taken wrong and none right


class Recorder:
    """Wraps one tracker's re-localisation steps and keeps, per frame index, what each step saw; poses are scored
    against the ground truth ``gt`` (by frame index) on ``pts`` once the first frame has set the alignment."""

    def __init__(self, tracker: SurgTracker, gt: list[np.ndarray], pts: np.ndarray, right: float) -> None:
        self.frames: dict[int, dict] = {}
        self.index = -1
        self.gt, self.pts, self.bound, self.align = gt, pts, right, np.eye(4)
        register, track = tracker.register, tracker.track
        refined, appearance, best = tracker._refined, tracker._appearance, tracker._best_candidate

        def on_register(frame, mask):
            pose = register(frame, mask)
            self.align = np.linalg.inv(pose) @ gt[frame.index]  # as `surgtrack eval` aligns
            return pose

        def on_track(frame, *args, **kwargs):
            self.index = frame.index
            return track(frame, *args, **kwargs)

        def on_refined(obs, feats, pose, edges, last):
            c = refined(obs, feats, pose, edges, last)
            self._now()["cands"].append({"start": self.right(pose, self.index),
                                         "refined": c is not None and self.right(c.node.pose, self.index),
                                         "pose": None if c is None else c.node.pose.copy(), "looks": None})
            return c

        def on_appearance(pose, points, values):
            looks = appearance(pose, points, values)
            for c in self._now()["cands"]:  # the refined candidate at this pose
                if c["pose"] is not None and c["looks"] is None and np.array_equal(c["pose"], pose):
                    c["looks"] = np.nan if looks is None else looks
                    break
            return looks

        def on_best(obs, feats, cands, last):
            now = self._now()
            drawn = tracker.rng.bit_generator.state
            held = refined(obs, feats, gt[self.index] @ np.linalg.inv(self.align), [], last)
            tracker.rng.bit_generator.state = drawn  # the run's random draws as they were
            found = best(obs, feats, cands, last)  # refines each candidate (`on_refined`)
            now["cands"], refined_here = [], now["cands"]
            true = obs.frame.mask
            on = true is not None and 2 * np.count_nonzero(obs.mask & (true > 0)) >= np.count_nonzero(obs.mask)
            now["sets"].append({"cands": refined_here, "on": on,
                                "truth": held is not None and self.right(held.node.pose, self.index),
                                "chosen": found is not None and self.right(found[0].pose, self.index)})
            return found

        tracker.register, tracker.track = on_register, on_track
        tracker._refined, tracker._appearance, tracker._best_candidate = on_refined, on_appearance, on_best

    def right(self, pose: np.ndarray, index: int) -> bool:
        """Whether ``pose`` (tracker's object frame) lies within the bound's ADD of frame ``index``'s truth."""
        return bool(add_errors([pose @ self.align], [self.gt[index]], self.pts)[0] < self.bound)

    def _now(self) -> dict:
        return self.frames.setdefault(self.index, {"cands": [], "sets": []})


def classify(attempt: dict, status: dict, out_right: bool, min_ncc: float) -> list[str]:
    """The classes of the module's list that fit one frame's re-localisation: the first that fits, and ``truth
    held`` beside ``taken wrong`` and ``none right``."""
    sets = attempt["sets"]
    cands = [c for s in sets for c in s["cands"]]
    kept = [c for c in cands if c["refined"]]
    held = (["truth held"] if any(s["truth"] for s in sets) else []) + (
        ["on it"] if any(s["on"] for s in sets) else [])
    if status["status"] == "relocalised":
        return ["taken right"] if out_right else ["right there"] if kept else ["taken wrong"] + held
    if any(s["chosen"] for s in sets):
        return ["lost after" if status.get("reason") in ("unsure", "seen past") else "silhouette"]
    if any(c["looks"] is None or np.isnan(c["looks"]) or c["looks"] >= min_ncc for c in kept):
        return ["beaten"]
    if kept:
        return ["appearance"]
    if any(c["start"] for c in cands):
        return ["refined off"]
    return ["none right"] + held


def main() -> None:
    ap = tracking_parser(__doc__.splitlines()[0])
    ap.add_argument("--first-mask-only", action="store_true")
    ap.add_argument("--right", type=float, default=0.03, help="ADD (m) below which a pose is right")
    a = ap.parse_args()
    cfg = tracker_config(a.config)
    names = sequence_names(a.data, a.only)
    total: Counter = Counter()
    print(f"{'sequence':<16}" + "".join(f"{c:>12}" for c in ("attempts",) + CLASSES + ALSO))
    for name in names:
        seq = open_sequence(a.data / name)
        gt_by_id = seq.gt_poses()
        gt = [gt_by_id[i] for i in seq.ids]
        tracker = SurgTracker(cfg)
        rec = Recorder(tracker, gt, model_points(seq.gt_visible_points(), seq.gt_model()), a.right)
        track_sequence(seq, a.out / name, cfg, first_mask_only=a.first_mask_only, tracker=tracker)
        log, est = read_track_log(a.out / name), read_poses(a.out / name / "ob_in_cam")
        counts: Counter = Counter()
        for index, attempt in sorted(rec.frames.items()):
            if attempt["sets"]:
                pose = est.get(log[index]["frame"])
                out_right = pose is not None and rec.right(pose, index)
                counts.update(classify(attempt, log[index], out_right, cfg.failure.relocalise_min_ncc))
        total += counts
        print(f"{name:<16}{sum(counts[c] for c in CLASSES):>12}" + "".join(f"{counts[c]:>12}" for c in CLASSES + ALSO),
              flush=True)
    print(f"{'all':<16}{sum(total[c] for c in CLASSES):>12}" + "".join(f"{total[c]:>12}" for c in CLASSES + ALSO))


if __name__ == "__main__":
    main()
