"""``kitti-eval inspect``: one frame's boxes labelled by the matching behind the AP, for one or more
models."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..core.protocol import METRICS
from ..errors import ConfigError
from .common import EXIT_OK, add_config_options, add_slot_options, config, emit


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "inspect",
        help="every box of one frame labelled by the matching, for one or more models",
        description="One frame, one or more models: every detection labelled by the matching behind the AP "
        "(TP with its ground truth and IoU, FP and why, ignored, DontCare, below the score threshold, "
        "other class) and the ground truth each model missed.",
    )
    p.add_argument("--gt", required=True, type=Path, help="ground truth")
    p.add_argument(
        "--pred", required=True, type=Path, action="append", help="predictions of a model; repeat for several models"
    )
    p.add_argument(
        "--name",
        action="append",
        default=[],
        help="a model's name, once per --pred in the same order (default: the folder after "
        "kitti_models/ in the path, else the file name)",
    )
    p.add_argument("--frame", required=True, help="frame id, e.g. 000015 (or 15)")
    add_slot_options(p, list(METRICS))
    p.add_argument(
        "--score-threshold",
        type=float,
        default=None,
        help="detections scoring below this take no part (default: all take part)",
    )
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("--output", "-o", type=Path)
    add_config_options(p)
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.inspection import inspect_frame, inspection_json, model_name, render_inspection, unique_names
    from ..io.loaders import load_detections, load_ground_truth_and_calibs

    if args.name and len(args.name) != len(args.pred):
        raise ConfigError(f"--name given {len(args.name)} times for {len(args.pred)} --pred")
    names = args.name or unique_names([model_name(p) for p in args.pred])  # inspect_frame refuses repeats
    gt, calibs = load_ground_truth_and_calibs(args.gt)
    models = [(name, load_detections(path, calibs=calibs, keep_lidar=True)) for name, path in zip(names, args.pred)]
    report = inspect_frame(
        gt,
        models,
        args.frame,
        config(args),
        cls=args.cls,
        metric=args.metric,
        difficulty=args.difficulty,
        oset=args.oset,
        score_threshold=args.score_threshold,
    )
    text = inspection_json(report) if args.format == "json" else render_inspection(report)
    emit(text, args.output)
    return EXIT_OK
