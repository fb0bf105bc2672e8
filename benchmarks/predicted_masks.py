"""The masks the tracker makes without given ones, against the true masks: which fails first, the mask or the pose?

    .venv/bin/python benchmarks/predicted_masks.py DATA OUT [--config C.json] [--only SEQ,SEQ] [--off 0.03]
                                                   [--true-masks] [--lost-on-true-masks]

Each sequence of DATA is tracked with its first mask only, as `surgtrack track --first-mask-only` tracks it (into
OUT/SEQ), and the mask each frame was tracked on (`SurgTracker._located`: the mask predicted at the predicted pose,
made again at the tracked one) is kept. Against the frame's true mask (the rendered sequence has every frame's),
over the pixels with depth (a mask made from depth holds no pixel without it): precision (the share of the mask on
the instrument) and recall (the share of the instrument in the mask). Against the ground truth (`surgtrack eval`'s
ADD-S, the first pose aligned): the first frame whose pose is more than ``--off`` (3 cm) off the instrument's
surface (ADD-S: a turn about a shaft does not count, since it puts the mask on nothing else), and the first frame
whose mask has a precision below one half (the mask took in more of something else than of the instrument). A mask
that goes off while its pose is still right is the mask's failure (a hand the model grew into); a pose that goes
off with a clean mask is the tracking's.

With ``--true-masks`` every mask the tracker would make is replaced by the frame's true mask, all else as without
masks (the Gauss-Newton steps, L_FS against the background, the checks, the model's growth from frames without a
given mask, the colour search while lost): the run's AUCs are what the first-mask-only path reaches with perfect
masks, so that #6's gap splits into what the masks cost and what the path without them costs with perfect ones.
``--lost-on-true-masks`` re-localises a lost instrument on the true mask (the mask made at the last pose,
replaced), as a run with every mask does, instead of searching the frame's colour regions; without
``--true-masks`` it measures what a perfect search while lost would give the masks the tracker makes.

Printed, one row a sequence: frames tracked on a made mask, the means of precision and recall, the first frame
precision fell below one half with the ADD-S there, the first frame the ADD-S passed ``--off`` with the precision
there, which came first, and the sequence's ADD-S / ADD AUC; then the mean AUCs. The default configuration is the
SDF off, whose poses do not depend on timing (the runs are then `surgtrack bench --first-mask-only`'s, pose file for
pose file).
"""

from __future__ import annotations

import numpy as np
from result_runs import sequence_names, tracker_config, tracking_parser

from surgtrack.io import Frame, open_sequence
from surgtrack.metrics import evaluate
from surgtrack.pipeline import track_sequence
from surgtrack.tracker import SurgTracker


def mask_scores(made: np.ndarray, true: np.ndarray, depth: np.ndarray) -> tuple[float, float]:
    """Precision and recall of the mask ``made`` against the ``true`` one over the pixels with ``depth`` (NaN where
    either holds none)."""
    made, true = made & (depth > 0), true & (depth > 0)
    both = np.count_nonzero(made & true)
    n_made, n_true = np.count_nonzero(made), np.count_nonzero(true)
    return (both / n_made if n_made else np.nan), (both / n_true if n_true else np.nan)


def record_masks(tracker: SurgTracker, true_masks: bool = False, lost_on_true: bool = False
                 ) -> dict[int, tuple[float, float]]:
    """Wrap ``tracker._located`` so that the mask of each frame tracked on (not re-localised) is scored against the
    frame's true mask; returns the scores by frame index, filled in as the tracker runs. With ``true_masks`` the
    tracker's masks (predicted, made again at the tracked pose) are the frames' true masks; with ``lost_on_true`` a
    lost instrument is re-localised on the true mask (given as the mask made at the last pose) instead of by the
    colour search (`_search`, which runs only with a colour model)."""
    scores: dict[int, tuple[float, float]] = {}
    located, predicted, colour = tracker._located, tracker._predicted_mask, tracker._colour

    def mask_for(frame: Frame, pose: np.ndarray, margin: int | None = None) -> np.ndarray:
        return frame.mask > 0 if true_masks or (lost_on_true and tracker.lost) else predicted(frame, pose, margin)

    def on_located(frame: Frame, mask: np.ndarray | None, clock, observed=None):
        lost = tracker.lost
        found = located(frame, mask, clock, observed)
        if not lost and not isinstance(found, str) and not found[0].mask_given and frame.mask is not None:
            scores[frame.index] = mask_scores(found[0].mask, frame.mask > 0, frame.depth)
        return found

    tracker._located, tracker._predicted_mask = on_located, mask_for
    if lost_on_true:
        tracker._colour = lambda: None if tracker.lost else colour()
    return scores


def first(frames: list[int], where: list[bool]) -> int | None:
    """The first of ``frames`` where ``where`` holds, None if none."""
    return next((i for i, w in zip(frames, where, strict=True) if w), None)


def which_first(mask_off: int | None, pose_off: int | None) -> str:
    """Which went off first, by the frames they went off at (None: never)."""
    if mask_off is None and pose_off is None:
        return "neither"
    if pose_off is None or (mask_off is not None and mask_off < pose_off):
        return "mask"
    return "pose" if mask_off is None or pose_off < mask_off else "together"


def main() -> None:
    ap = tracking_parser(__doc__.splitlines()[0])
    ap.add_argument("--off", type=float, default=0.03, help="ADD-S (m) beyond which a pose is off")
    ap.add_argument("--true-masks", action="store_true", help="the masks the tracker makes replaced by the true ones")
    ap.add_argument("--lost-on-true-masks", action="store_true",
                    help="re-localise a lost instrument on its true mask, not by the colour search")
    a = ap.parse_args()
    cfg = tracker_config(a.config)
    names = sequence_names(a.data, a.only)
    print(f"{'sequence':<16}{'masks':>6}{'precision':>10}{'recall':>8}  {'mask off: frame, ADD-S cm':<26}"
          f"{'pose off: frame, precision':<27}{'first':<9}ADD-S / ADD")
    aucs = []
    for name in names:
        seq = open_sequence(a.data / name)
        tracker = SurgTracker(cfg)
        scores = record_masks(tracker, a.true_masks, a.lost_on_true_masks)
        track_sequence(seq, a.out / name, cfg, first_mask_only=True, tracker=tracker)
        result = evaluate(a.out / name, seq)
        aucs.append((result["add_s_auc"], result["add_auc"]))
        frames = sorted(scores)
        # None where the frame was lost after its mask was made (the checks that follow the solve)
        errors = [result["errors"]["add_s"].get(seq.ids[i]) for i in frames]
        precision = np.array([scores[i][0] for i in frames])
        recall = np.array([scores[i][1] for i in frames])
        mask_off = first(frames, list(precision < 0.5))
        pose_off = first(frames, [e is not None and e > a.off for e in errors])
        at = dict(zip(frames, errors, strict=True))
        mask_cell = "-" if mask_off is None else (
            f"{mask_off}, {'lost' if at[mask_off] is None else f'{100 * at[mask_off]:.1f}'}")
        pose_cell = "-" if pose_off is None else f"{pose_off}, {scores[pose_off][0]:.2f}"
        print(f"{name:<16}{len(frames):>6}{np.nanmean(precision):>10.2f}{np.nanmean(recall):>8.2f}  "
              f"{mask_cell:<26}{pose_cell:<27}{which_first(mask_off, pose_off):<9}"
              f"{aucs[-1][0]:.2f} / {aucs[-1][1]:.2f}", flush=True)
    print(f"{'mean':<16}{'':>76}{np.mean([s for s, _ in aucs]):.2f} / {np.mean([d for _, d in aucs]):.2f}")


if __name__ == "__main__":
    main()
