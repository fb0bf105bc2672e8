"""Run a tracker over a recorded sequence: masks policy, output files as frames are tracked, timing."""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

from .config import TrackerConfig
from .io import Frame, ResultWriter, Sequence, SequenceError, write_text_atomic
from .tracker import LOST, RELOCALISED, SurgTracker, TrackResult


@dataclass
class RunSummary:
    """Counts and speed of one run; ``lost_because`` counts the lost frames by `TrackResult.reason`; ``unmeasured``
    the posed frames that left a turn or a slide unmeasured (`TrackResult.unmeasured`), by kind; ``stage_ms`` is
    the mean time per frame of each tracking stage; ``sdf_frames`` the frames whose pose had L_SDF (eq. 11) in its
    graph, ``sdf_from`` the first of them (None: none had)."""

    frames: int = 0
    lost: int = 0
    lost_because: Counter[str] = field(default_factory=Counter)
    relocalised: int = 0
    unmeasured: Counter[str] = field(default_factory=Counter)
    sdf_frames: int = 0
    sdf_from: int | None = None
    seconds: float = 0.0
    stage_s: dict[str, float] = field(default_factory=dict)  # total seconds of each stage over the tracked frames

    @property
    def fps(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else 0.0

    @property
    def stage_ms(self) -> dict[str, float]:
        """Mean ms per tracked frame of each stage (the registered first frame has none)."""
        n = max(self.frames - 1, 1)
        return {k: v * 1e3 / n for k, v in self.stage_s.items()}

    def add(self, index: int, result: TrackResult) -> None:
        """Count frame ``index``'s result. Frame 0, registered from its mask, counts as a frame and by what it left
        unmeasured (against a registered model) only."""
        self.frames += 1
        self.unmeasured.update(result.unmeasured_kinds)
        if index == 0:
            return
        if result.status == LOST:
            self.lost += 1
            self.lost_because[result.reason] += 1
        self.relocalised += result.status == RELOCALISED
        self.sdf_frames += result.sdf
        if result.sdf and self.sdf_from is None:
            self.sdf_from = index
        for k, v in result.timings.items():
            self.stage_s[k] = self.stage_s.get(k, 0.0) + v

    def line(self) -> str:
        """The run in one line: frames, lost (and why), re-localised, frames with a turn or slide unmeasured, L_SDF,
        frames/s and ms per stage."""
        sdf = f"L_SDF from frame {self.sdf_from} on {self.sdf_frames}" if self.sdf_frames else "no L_SDF"
        stages = ", ".join(f"{k} {v:.1f}" for k, v in self.stage_ms.items())
        why = ", ".join(f"{n} {k}" for k, n in self.lost_because.most_common())
        lost = f"{self.lost} lost ({why})" if why else f"{self.lost} lost"
        free = "".join(f", {k} unmeasured on {n}" for k, n in sorted(self.unmeasured.items()))
        return (f"{self.frames} frames, {lost}, {self.relocalised} relocalised{free}, {sdf}, "
                f"{self.fps:.1f} frames/s ({stages} ms)")

    def write(self, out: Path) -> None:
        """OUT/summary.json, written as config.json and the poses are (`io.write_text_atomic`)."""
        write_text_atomic(out / "summary.json", json.dumps(self.to_dict(), indent=2))

    def to_dict(self) -> dict:
        return {"frames": self.frames, "lost": self.lost, "lost_because": dict(self.lost_because),
                "relocalised": self.relocalised, "unmeasured": dict(sorted(self.unmeasured.items())),
                "sdf_frames": self.sdf_frames, "sdf_from": self.sdf_from,
                "seconds": round(self.seconds, 3), "fps": round(self.fps, 2),
                "stage_ms": {k: round(v, 2) for k, v in self.stage_ms.items()}}


def frame_record(result: TrackResult) -> dict:
    """A frame's line of OUT/track.jsonl beside its frame id: status (and why, when lost), confidence, whether L_SDF
    (eq. 11) was in its graph, for a posed frame the directions its data left free (``"unmeasured"``: a list of
    ``{"turn": axis}`` or ``{"slide": axis}``, unit vectors in the object frame), for a posed frame tracked on a
    mask the tracker made how instrument-like that mask looks (``"colour"``, `TrackResult.colour`), and ms per
    stage."""
    why = {"reason": result.reason} if result.status == LOST else {}
    free = {} if result.status == LOST else {
        "unmeasured": [{u.kind: [round(float(a), 3) for a in u.axis]} for u in result.unmeasured]}
    made = {} if result.colour is None else {"colour": round(result.colour, 3)}
    return {"status": result.status, **why, "confidence": round(result.confidence, 4), "sdf": result.sdf, **free,
            **made, "ms": {k: round(v * 1e3, 2) for k, v in result.timings.items()}}


def track_sequence(
    seq: Sequence,
    out: Path | str,
    config: TrackerConfig | None = None,
    first_mask_only: bool = False,
    on_frame: Callable[[Frame, TrackResult], None] | None = None,
    tracker: SurgTracker | None = None,
) -> RunSummary:
    """Track every frame of ``seq`` and write OUT/ob_in_cam/, OUT/track.jsonl, OUT/config.json (and OUT/mesh.ply
    when the tracker reconstructs one). Per-frame masks are used when present unless ``first_mask_only``."""
    config = config or TrackerConfig()
    tracker = tracker or SurgTracker(config)
    out = Path(out)
    summary = RunSummary()
    # Frames that come with their mask are preprocessed and their features found in the reader's thread, while the
    # frame before is tracked (`SurgTracker.observe`: it depends on the frame alone, so the poses are the same).
    observe = tracker.observe if isinstance(tracker, SurgTracker) and not first_mask_only else None
    # closing: a run that stops on an error stops its frame reader too, not when the generator is collected
    with ResultWriter(out, config.to_dict()) as writer, closing(seq.read_ahead(1, prepare=observe)) as frames:
        t0 = time.perf_counter()
        first = seq[0]
        assert first.mask is not None  # the readers guarantee a first-frame mask
        try:
            pose = tracker.register(first, first.mask)
        except ValueError as e:
            raise SequenceError(seq.root, str(e)) from None
        registered = tracker.first_result(pose)
        writer.write(first.id, pose, frame_record(registered))
        summary.add(0, registered)
        if on_frame is not None:
            on_frame(first, registered)
        for i, (frame, observed) in enumerate(frames, start=1):
            if observed is None:
                result = tracker.track(frame, None if first_mask_only else frame.mask)
            else:
                result = tracker.track(frame, frame.mask, observed)
            writer.write(frame.id, result.pose, frame_record(result))
            summary.add(i, result)
            if on_frame is not None:
                on_frame(frame, result)
        summary.seconds = time.perf_counter() - t0
        mesh = getattr(tracker, "mesh", lambda: None)()
        if mesh is not None:
            writer.write_mesh(mesh)
    summary.write(out)
    return summary

