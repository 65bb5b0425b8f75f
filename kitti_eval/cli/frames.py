"""``kitti-eval frames``: hits, false positives and misses of every frame, from the AP's own matching."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..analysis.frame_question import ASKED
from ..core.protocol import OVERLAP_METRIC_NAMES
from ..errors import ConfigError
from .common import EXIT_OK, add_config_options, add_slot_options, config, emit, several_gt


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "frames",
        help="hits, false positives and misses per frame",
        description="True positives, false positives and misses of every frame for one class, metric and "
        "difficulty, from the same matching as the AP; --worst N lists the frames with most errors.",
    )
    p.add_argument(
        "--gt", required=True, nargs="+", action="extend", type=Path, help="ground truth (with --sharded: the shards)"
    )
    p.add_argument("--pred", required=True, nargs="+", action="extend", help="predictions (with --sharded: the shards)")
    p.add_argument("--sharded", action="store_true", help="--gt and --pred are shards of one set, read part by part")
    add_slot_options(p, list(OVERLAP_METRIC_NAMES))
    p.add_argument(
        "--score-threshold",
        type=float,
        default=ASKED.score_threshold,
        help="count detections scoring at least this (default 0: every detection)",
    )
    p.add_argument("--worst", type=int, metavar="N", help="only the N frames with most errors (FP + FN)")
    p.add_argument("--format", choices=["table", "csv", "json"], default="table")
    p.add_argument("--output", "-o", type=Path)
    add_config_options(p)
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..analysis.diagnostics import FrameQuestion, frame_stats, render_frames
    from ..io.loaders import load_pair

    if args.worst is not None and args.worst < 1:
        raise ConfigError("--worst must be >= 1")
    question = FrameQuestion(args.cls, args.metric, args.difficulty, args.oset, args.score_threshold)
    if args.sharded:
        from ..analysis.batch import expand_predictions
        from ..analysis.sharded import frame_stats_sharded

        stats = frame_stats_sharded(expand_predictions(args.gt), expand_predictions(args.pred), config(args), question)
    else:
        if len(args.gt) > 1:
            raise several_gt(args.gt)
        if len(args.pred) > 1:
            raise ConfigError("one --pred, or --sharded for a set in many files")
        stats = frame_stats(*load_pair(args.gt[0], Path(args.pred[0])), config(args), question)
    text = render_frames(stats, args.format, worst=args.worst)
    emit(text, args.output)
    return EXIT_OK
