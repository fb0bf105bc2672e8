"""Figures of the evaluation protocol (DESIGN.md section 4): accuracy-threshold curves and error over time.

Every function takes errors keyed by method name, so one call compares several methods (``surgtrack bench``);
``surgtrack eval`` passes a single method. Errors are in metres; None or inf marks a frame without a pose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from .metrics import AUC_MAX_ERR, auc

Errors = Sequence[float | None] | Mapping[str, float | None]


def _figure(width: float, height: float) -> tuple[Figure, Axes]:
    """A figure drawn by the Agg backend, independent of pyplot's global state."""
    fig = Figure(figsize=(width, height), dpi=120)
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot()


def _values(errors: Errors) -> np.ndarray:
    vals = errors.values() if isinstance(errors, Mapping) else errors
    return np.array([np.inf if e is None else float(e) for e in vals], dtype=np.float64)


def accuracy_curve(errors: Errors, max_err: float = AUC_MAX_ERR) -> tuple[np.ndarray, np.ndarray]:
    """Step points of the accuracy-threshold curve: thresholds x on [0, max_err] (m) at each error, and y, the
    fraction of all frames (missing ones included) whose error is at most x. Draw with steps after each point."""
    e = np.sort(_values(errors))
    kept = e[e < max_err]
    x = np.concatenate([[0.0], kept, [max_err]])
    if e.size == 0:
        return x, np.zeros_like(x)
    return x, np.searchsorted(e, x, side="right") / e.size


def plot_accuracy(
    errors_by_method: Mapping[str, Errors], path: Path | str, metric: str = "ADD", max_err: float = AUC_MAX_ERR
) -> Path:
    """Accuracy-threshold curve of each method for one metric, its AUC in the legend; writes a PNG, returns its path."""
    path = Path(path)
    fig, ax = _figure(5, 4)
    for name, errors in errors_by_method.items():
        x, y = accuracy_curve(errors, max_err)
        ax.step(x * 100.0, y * 100.0, where="post", label=f"{name} (AUC {auc(_values(errors), max_err):.2f})")
    ax.set_xlim(0, max_err * 100.0)
    ax.set_ylim(0, 100)
    ax.set_xlabel(f"{metric} threshold (cm)")
    ax.set_ylabel("accuracy (%)")
    ax.set_title(f"{metric} accuracy-threshold curve")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize="small")
    fig.tight_layout()
    fig.savefig(path)
    return path


def plot_errors_over_time(
    errors_by_method: Mapping[str, Errors], path: Path | str, metric: str = "ADD"
) -> Path:
    """Per-frame error (cm) of each method against frame index; frames without a pose are marked x on the axis."""
    path = Path(path)
    fig, ax = _figure(7, 3.5)
    for name, errors in errors_by_method.items():
        e = _values(errors)
        t = np.arange(len(e))
        finite = np.isfinite(e)
        (line,) = ax.plot(t, np.where(finite, e * 100.0, np.nan), label=name, lw=1.2)
        if (~finite).any():
            ax.plot(t[~finite], np.zeros((~finite).sum()), "x", color=line.get_color(), clip_on=False,
                    label=f"{name}: no pose")
    ax.set_xlabel("frame")
    ax.set_ylabel(f"{metric} error (cm)")
    ax.set_ylim(bottom=0)
    ax.set_title(f"{metric} error over time")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")
    fig.tight_layout()
    fig.savefig(path)
    return path


def plot_evaluation(result: Mapping, out_dir: Path | str, method: str = "surgtrack") -> list[Path]:
    """The figures of one :func:`surgtrack.metrics.evaluate` result: ADD and ADD-S curves and ADD over time."""
    out = Path(out_dir)
    errors = result["errors"]
    return [
        plot_accuracy({method: errors["add"]}, out / "accuracy_add.png", "ADD"),
        plot_accuracy({method: errors["add_s"]}, out / "accuracy_add_s.png", "ADD-S"),
        plot_errors_over_time({f"{method} ADD": errors["add"], f"{method} ADD-S": errors["add_s"]},
                              out / "errors_over_time.png", "pose"),
    ]
