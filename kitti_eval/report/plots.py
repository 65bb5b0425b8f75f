"""Precision-recall curves as PNG files (matplotlib, the ``plot`` extra), like the devkit's plots.

The devkit samples precision at 41 recall positions (0, 1/40, ..., 1), max-interpolated; these are the
curves behind R11 and R40 (``--curves`` puts the same numbers in the JSON).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ..core.protocol import DEFAULT_METRIC, DEFAULT_OSET, METRICS, N_SAMPLE_PTS, Difficulty
from ..core.result import EvalResult
from ..errors import ConfigError

__all__ = ["plot_pr_curves", "plot_overlays"]

_RECALL = [i / (N_SAMPLE_PTS - 1) for i in range(N_SAMPLE_PTS)]


def _pyplot() -> Any:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ConfigError("plots need matplotlib: pip install 'kitti-eval[plot]'") from None
    return plt


def _curve(result: EvalResult, oset: str, cls: str, metric: str, difficulty: str) -> list[float] | None:
    if result.curves is None:
        raise ValueError("the result holds no curves: evaluate with keep_curves=True")
    curve = result.curves[oset][cls][metric].get(difficulty)
    if curve is None:
        return None
    values = curve.orientation if metric == "aos" else curve.precision
    return [float(v) for v in values]


def _save(plt: Any, fig: Any, ax: Any, path: Path, title: str, ylabel: str) -> Path:
    """Label a curve plot the same way everywhere, write it, and free the figure."""
    ax.set(xlim=(0, 1), ylim=(0, 1.02), xlabel="recall", ylabel=ylabel, title=title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def plot_pr_curves(result: EvalResult, out_dir: str | Path, *, oset: str = DEFAULT_OSET) -> list[Path]:
    """One PNG per class and metric, easy / moderate / hard together; returns the files written."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for cls in result.classes:
        for metric in METRICS:
            curves = {d.label: _curve(result, oset, cls, metric, d.label) for d in Difficulty}
            if all(c is None for c in curves.values()):
                continue
            fig, ax = plt.subplots(figsize=(5, 4), dpi=110)
            for label, values in curves.items():
                if values is not None:
                    ap = result.ap[oset]["R40"][cls][metric][label]
                    ax.plot(_RECALL, values, label=f"{label} (AP R40 {ap:.2f})")
            iou = result.overlaps[cls][oset]["bbox" if metric == "aos" else metric]
            written.append(
                _save(
                    plt,
                    fig,
                    ax,
                    out / f"{cls}_{metric}_{oset}.png",
                    f"{cls} {metric} (IoU {iou:.2f})",
                    "orientation similarity" if metric == "aos" else "precision",
                )
            )
    return written


def plot_overlays(
    named: Sequence[tuple[str, EvalResult]],
    out_dir: str | Path,
    *,
    metric: str = DEFAULT_METRIC,
    difficulty: str = "moderate",
    oset: str = DEFAULT_OSET,
) -> list[Path]:
    """One PNG per class overlaying the curves of several results (e.g. checkpoints or models)."""
    plt = _pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    classes = list(named[0][1].classes) if named else []
    for cls in classes:
        fig, ax = plt.subplots(figsize=(5.5, 4), dpi=110)
        drawn = 0
        for name, result in named:
            values = _curve(result, oset, cls, metric, difficulty) if cls in result.classes else None
            if values is not None:
                ax.plot(_RECALL, values, label=f"{name} ({result.ap[oset]['R40'][cls][metric][difficulty]:.2f})")
                drawn += 1
        if not drawn:
            plt.close(fig)
            continue
        written.append(
            _save(
                plt,
                fig,
                ax,
                out / f"{cls}_{metric}_{difficulty}_overlay.png",
                f"{cls} {metric} {difficulty}: {len(named)} results",
                "precision",
            )
        )
    return written
