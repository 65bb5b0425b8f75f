"""``kitti-eval errors``: why AP is lost, the AP each error type costs and how far the matched boxes are
off (the rules are in :mod:`kitti_eval.analysis.decomposition`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..core.protocol import THRESHOLD_SETS
from .common import EXIT_OK, add_config_options, config, emit, say, start_warm_up, wait


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "errors",
        help="why AP is lost: the AP each error type costs, and how far the matched boxes are off",
        description="Error decomposition (TIDE's types on KITTI's matching: classification, localization, both, "
        "duplicate, background, missed; orientation for AOS): the AP points gained by fixing each type alone, "
        "per class, metric and difficulty. True-positive errors (nuScenes): translation, scale and orientation "
        "of the boxes the 3D matching pairs. The rules are in kitti_eval/analysis/decomposition.py.",
    )
    p.add_argument("--gt", required=True, type=Path, help="ground truth")
    p.add_argument("--pred", required=True, type=Path, help="predictions")
    p.add_argument("--set", dest="oset", default="strict", choices=list(THRESHOLD_SETS), help="IoU threshold set")
    p.add_argument("--recall", default="R40", choices=["R40", "R11"], help="AP scale of the table (JSON holds both)")
    p.add_argument("--format", choices=["table", "json", "markdown"], default="table")
    p.add_argument("--output", "-o", type=Path, help="write the result here instead of stdout")
    p.add_argument("--quiet", "-q", action="store_true", help="do not print warnings")
    add_config_options(p)
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.decomposition import decompose_plan, render_errors
    from ..core.evaluation import plan_evaluation
    from ..io.reading import read_pair

    cfg = config(args)
    warmer = start_warm_up(decomposition=True)
    pair = read_pair(args.gt, args.pred)
    gt, dt, load_warnings = pair.gt, pair.dt, pair.warnings
    wait(warmer)
    plan = plan_evaluation(gt, dt, cfg)
    text = render_errors(decompose_plan(plan, oset=args.oset), args.format, recall=args.recall)
    if not args.quiet:
        for w in [*load_warnings, *plan.warnings]:
            say(f"warning: {w}")
    emit(text, args.output)
    return EXIT_OK
