"""``kitti-eval demo``: the main job on the bundled synthetic set (nothing is downloaded)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .common import EXIT_OK, add_eval_options
from .evaluate import run_pair


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="evaluate the bundled demo set",
        description="Evaluate the bundled synthetic demo set (nothing is downloaded).",
    )
    add_eval_options(p)
    p.add_argument(
        "--where",
        action="store_true",
        help="print the demo's paths, one a line, and exit: its ground truth, its predictions and a weaker "
        "model's predictions (for compare and gate --baseline)",
    )
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..demo import demo_paths, demo_weaker_path

    gt_path, pred_path = demo_paths()
    if args.where:
        # one write, whatever the buffering (PYTHONUNBUFFERED=1 writes each print at once): a reader that stops
        # after the first line, as `kitti-eval demo --where | head -n 1` does, never finds the pipe closed
        sys.stdout.write("".join(f"{path}\n" for path in (gt_path, pred_path, demo_weaker_path())))
        return EXIT_OK
    return run_pair(gt_path, pred_path, args)
