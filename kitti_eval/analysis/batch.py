"""Many result files against one ground truth: one warm process, a table over checkpoints, the best named.

    kitti-eval --gt kitti_infos_val.pkl --pred 'output/*/eval/epoch_*/val/result.pkl'

The ground truth is loaded once; each prediction file is loaded and evaluated in turn (the kernels stay
compiled), with a progress bar on stderr. A checkpoint is labelled by its path; its epoch, when the path
holds ``epoch_N``, orders the table and the optional plot of AP against epoch.
"""

from __future__ import annotations

import glob
import json
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..core.evaluation import evaluate
from ..core.frames import Annotations
from ..core.protocol import EvalConfig
from ..core.result import EvalResult
from ..errors import ConfigError, InputError
from ..io.loaders import load_detections

if TYPE_CHECKING:  # imported where used: the main job expands its globs here and needs no gate rules
    from ..core.result import ValueKey

__all__ = ["expand_predictions", "Checkpoint", "evaluate_many", "default_ranking", "render_batch", "plot_batch"]

_EPOCH = re.compile(r"epoch[_-]?(\d+)", re.IGNORECASE)


def expand_predictions(patterns: Sequence[str | Path]) -> list[Path]:
    """Paths and glob patterns (``*``, ``?``, ``[``) to existing files or folders, in order, without repeats."""
    out: list[Path] = []
    for pattern in patterns:
        text = str(pattern)
        if Path(text).exists() or not any(ch in text for ch in "*?["):
            matches = [text]
        else:
            matches = sorted(glob.glob(text, recursive=True), key=_natural)
            if not matches:
                raise InputError(f"no file matches {text!r}", source=text)
        for m in matches:
            p = Path(m)
            if p not in out:
                out.append(p)
    return out


def _natural(text: str) -> list[object]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", text)]


def epoch_of(path: Path) -> int | None:
    found = _EPOCH.findall(str(path))
    return int(found[-1]) if found else None


@dataclass(frozen=True)
class Checkpoint:
    path: Path
    epoch: int | None
    result: EvalResult

    @property
    def label(self) -> str:
        """How tables and plots name it: its epoch, else its path."""
        return f"epoch {self.epoch}" if self.epoch is not None else str(self.path)


def default_ranking(result: EvalResult) -> float:
    """Mean of the moderate 3D AP (R40, strict) over the classes evaluated; the default 'best' score."""
    values = [result.get(cls, "3d", "moderate") for cls in result.classes]
    present = [v for v in values if v is not None]
    return sum(present) / len(present) if present else -math.inf


def evaluate_many(
    gt: Annotations,
    paths: Sequence[Path],
    config: EvalConfig | None = None,
    *,
    progress: bool = True,
    on_error: Callable[[Path, Exception], None] | None = None,
    keep_curves: bool = False,
) -> list[Checkpoint]:
    """Evaluate every prediction file against ``gt``; a bad file raises unless ``on_error`` takes it."""
    from tqdm import tqdm

    out: list[Checkpoint] = []
    bar = tqdm(paths, desc="evaluating", unit="file", disable=not progress, leave=False)
    for path in bar:
        bar.set_postfix_str(path.name)
        try:
            result = evaluate(gt, load_detections(path), config, keep_curves=keep_curves)
        except InputError as e:
            if on_error is None:
                raise
            on_error(path, e)
            continue
        out.append(Checkpoint(path, epoch_of(path), result))
    out.sort(key=lambda c: (c.epoch is None, c.epoch if c.epoch is not None else 0, _natural(str(c.path))))
    return out


def _columns(results: Sequence[Checkpoint], keys: Sequence[ValueKey] | None) -> list[ValueKey]:
    if keys:
        return list(keys)
    from ..core.result import ValueKey

    classes = results[0].result.classes if results else ()
    return [ValueKey(cls, "3d", "moderate") for cls in classes]


def render_batch(
    results: Sequence[Checkpoint],
    fmt: str = "table",
    *,
    keys: Sequence[ValueKey] | None = None,
    best_by: ValueKey | None = None,
) -> str:
    """A table over checkpoints (rows) and values (columns: moderate 3D AP per class by default)."""
    if not results:
        raise InputError("no prediction file could be evaluated")
    cols = _columns(results, keys)

    def score(c: Checkpoint) -> float:
        if best_by is None:
            return default_ranking(c.result)
        v = best_by.read(c.result.to_dict())
        return -math.inf if v is None else v

    best = max(results, key=score)
    how = f"by {best_by}" if best_by else "by mean moderate 3D AP (R40, strict)"
    if fmt == "json":
        doc: dict[str, Any] = {
            "schema_version": 1,
            "best": {"path": str(best.path), "epoch": best.epoch, "ranked": how},
            "results": [{"path": str(c.path), "epoch": c.epoch, "result": c.result.to_dict()} for c in results],
        }
        return json.dumps(doc, indent=2, allow_nan=False) + "\n"

    def cell(v: float | None) -> str:
        return "-" if v is None else f"{v:.2f}"

    names = [str(k) for k in cols]
    rows = [[c.label] + [cell(k.read(c.result.to_dict())) for k in cols] for c in results]
    if fmt == "markdown":
        lines = ["| checkpoint | " + " | ".join(f"`{n}`" for n in names) + " |", "|---|" + "---:|" * len(names)]
        lines += ["| " + " | ".join(r) + (" ⭐" if c is best else "") + " |" for r, c in zip(rows, results)]
        return "\n".join(lines) + f"\n\nBest: **{best.label}** ({best.path}), {how}.\n"
    widths = [max(len(r[i]) for r in rows + [["checkpoint", *names]]) for i in range(len(names) + 1)]
    header = "  ".join(
        h.ljust(widths[0]) if i == 0 else h.rjust(widths[i]) for i, h in enumerate(["checkpoint", *names])
    )
    lines = [header]
    for r, c in zip(rows, results):
        lines.append(
            "  ".join(v.ljust(widths[0]) if i == 0 else v.rjust(widths[i]) for i, v in enumerate(r))
            + ("  <- best" if c is best else "")
        )
    lines.append(f"best: {best.label} ({best.path}), {how}")
    return "\n".join(lines) + "\n"


def plot_batch(results: Sequence[Checkpoint], path: str | Path, *, keys: Sequence[ValueKey] | None = None) -> None:
    """A PNG of each value against epoch (checkpoint order when epochs are unknown); needs matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ConfigError("--plot needs matplotlib: pip install 'kitti-eval[plot]'") from None
    cols = _columns(results, keys)
    xs = [c.epoch if c.epoch is not None else i for i, c in enumerate(results)]
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=120)
    for key in cols:
        ys = [key.read(c.result.to_dict()) for c in results]
        ax.plot(xs, [math.nan if y is None else y for y in ys], marker="o", label=str(key))
    ax.set_xlabel("epoch" if all(c.epoch is not None for c in results) else "checkpoint")
    ax.set_ylabel("AP (%)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("KITTI AP by checkpoint")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
