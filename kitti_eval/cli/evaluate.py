"""``kitti-eval --gt GT --pred PRED``: the main job, no command name. One prediction file is evaluated
and printed; several (or a glob) are checkpoints, tabled side by side; ``--sharded`` files are parts of
one set."""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path
from typing import Any

from .. import __version__
from ..errors import ConfigError
from ..report.render import OutputFormat
from .common import (
    EXIT_INPUT,
    EXIT_OK,
    add_eval_options,
    config,
    emit,
    say,
    several_gt,
    start_warm_up,
    wait,
    wrote,
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The main job's options, on the program's own parser (before the commands), and the program's version."""
    p.add_argument("--version", action="version", version=f"{p.prog} {__version__}")
    p.add_argument(
        "--gt",
        nargs="+",
        action="extend",
        type=Path,
        metavar="GT",
        help="ground truth: a KITTI label_2 folder or an OpenPCDet infos .pkl[.gz]; several files (or a glob) "
        "only with --sharded",
    )
    p.add_argument(
        "--pred",
        nargs="+",
        action="extend",
        metavar="PRED",
        help="predictions: a KITTI result folder (16-field txt) or an OpenPCDet result .pkl[.gz]; "
        "several files, repeated or a glob ('output/*/epoch_*/val/result.pkl'), evaluate many "
        "checkpoints in one process",
    )
    add_eval_options(p)
    from ..io.formats import FORMATS

    fmts = p.add_argument_group("input formats")
    fmts.add_argument(
        "--gt-format", choices=FORMATS, default=None, help="the ground truth's layout, instead of detecting it"
    )
    fmts.add_argument(
        "--pred-format", choices=FORMATS, default=None, help="the predictions' layout, instead of detecting it"
    )
    fmts.add_argument(
        "--split",
        type=Path,
        metavar="IMAGESETS_TXT",
        help="evaluate only the frames listed in this file (ImageSets/val.txt: one id a line); "
        "predictions for other frames are dropped with a warning",
    )
    shards = p.add_argument_group("a set in many files")
    shards.add_argument(
        "--sharded",
        action="store_true",
        help="the --gt files (a quoted glob) and the --pred files (globs or repeated) are shards of ONE set, "
        "evaluated part by part in bounded memory; frames are matched by id across files",
    )
    shards.add_argument(
        "--cluster",
        metavar="ADDRESS",
        help="with --sharded: run the parts on Dask, 'local:N' (N worker processes on this machine) or a "
        "scheduler's 'tcp://HOST:8786' (needs the cluster extra)",
    )
    many = p.add_argument_group("many checkpoints")
    many.add_argument(
        "--value",
        action="append",
        default=[],
        metavar="KEY",
        help="a column of the checkpoint table, e.g. Car/3d/moderate/R40 (default: moderate 3D "
        "AP of each class); repeatable",
    )
    many.add_argument("--best-by", metavar="KEY", help="rank checkpoints by this value (default: mean moderate 3D AP)")
    many.add_argument("--plot", type=Path, metavar="PNG", help="save a plot of AP against epoch (needs matplotlib)")
    p.add_argument(
        "--plot-dir",
        type=Path,
        metavar="DIR",
        help="save precision-recall curves as PNGs (per class and metric; with several --pred, one "
        "overlay per class of the moderate 3D curves); needs matplotlib",
    )
    from .remote import add_service_arguments

    add_service_arguments(p)


def run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """The main job: one pair, many checkpoints, or a sharded set, as the options say."""
    if args.gt is None or not args.pred:
        parser.error("the following arguments are required: --gt, --pred (or a command)")
    if args.service:
        from .remote import run_evaluation

        return run_evaluation(args)
    from ..analysis.batch import expand_predictions

    if args.sharded or args.cluster:
        return run_sharded(args)
    if len(args.gt) > 1:
        raise several_gt(args.gt)
    gt = args.gt[0]
    preds = expand_predictions(args.pred)
    if len(preds) == 1 and not args.plot and not (args.plot_dir and len(args.pred) > 1):
        return run_pair(gt, preds[0], args)
    if args.gt_format or args.pred_format or args.split or args.errors:
        raise ConfigError("--gt-format, --pred-format, --split and --errors work with one --pred only")
    return run_many(gt, preds, args)


def run_pair(gt_path: Path, pred_path: Path, args: argparse.Namespace) -> int:
    """Evaluate one prediction file against the ground truth and write the result (``demo`` too)."""
    from ..core.evaluation import evaluate
    from ..io.reading import LoadOptions, read_pair
    from ..report.render import render

    cfg = config(args)
    warmer = start_warm_up(decomposition=getattr(args, "errors", False))
    pair = read_pair(
        gt_path,
        pred_path,
        gt_format=getattr(args, "gt_format", None),
        options=LoadOptions(fmt=getattr(args, "pred_format", None)),
        split=getattr(args, "split", None),
    )
    gt, dt, load_warnings = pair.gt, pair.dt, pair.warnings
    wait(warmer)
    plot_dir = getattr(args, "plot_dir", None)
    keep_curves = args.curves or bool(plot_dir)
    extra: dict[str, Any] | None = None
    if args.errors:
        from ..analysis.decomposition import errors_document, evaluate_with_errors, render_errors

        result, decomposition = evaluate_with_errors(gt, dt, cfg, keep_curves=keep_curves)
        extra = errors_document(decomposition, full=False)
    else:
        result = evaluate(gt, dt, cfg, keep_curves=keep_curves)
    if plot_dir:
        from ..report.plots import plot_pr_curves

        wrote(plot_dir, f"{len(plot_pr_curves(result, plot_dir))} precision-recall PNGs to")
    text = render(result, args.format, include_curves=args.curves, extra=extra)
    if args.errors and args.format is not OutputFormat.JSON:
        text += "\n" + render_errors(decomposition, args.format.value)
    if not args.quiet:
        for w in [*load_warnings, *result.warnings]:
            say(f"warning: {w}")
    emit(text, args.output)
    return EXIT_OK


def run_sharded(args: argparse.Namespace) -> int:
    from ..analysis.batch import expand_predictions
    from ..analysis.cluster import cluster_mapper, progress_mapper
    from ..analysis.sharded import evaluate_sharded
    from ..report.render import render

    if not args.sharded:
        raise ConfigError("--cluster evaluates a set given in shards: add --sharded")
    if args.errors:
        raise ConfigError("--errors works with one --gt and one --pred, not with --sharded")
    if args.split or args.plot or args.plot_dir:
        raise ConfigError("--split, --plot and --plot-dir do not work with --sharded")
    cfg = config(args)
    gts = expand_predictions(args.gt)
    preds = expand_predictions(args.pred)
    show = sys.stderr.isatty() and not args.quiet
    context = cluster_mapper(args.cluster, progress=show) if args.cluster else contextlib.nullcontext(None)
    with context as mapper:
        result = evaluate_sharded(
            gts,
            preds,
            cfg,
            gt_format=args.gt_format,
            pred_format=args.pred_format,
            keep_curves=args.curves,
            mapper=mapper or progress_mapper(show),
            source=(", ".join(str(g) for g in args.gt), ", ".join(str(p) for p in args.pred)),
        )
    if not args.quiet:
        for w in result.warnings:
            say(f"warning: {w}")
    emit(render(result, args.format, include_curves=args.curves), args.output)
    return EXIT_OK


def run_many(gt_path: Path, preds: list[Path], args: argparse.Namespace) -> int:
    from ..analysis.batch import evaluate_many, plot_batch, render_batch
    from ..core.result import ValueKey
    from ..io.loaders import load_ground_truth

    cfg = config(args)
    keys = [ValueKey.parse(k) for k in args.value]
    best_by = ValueKey.parse(args.best_by) if args.best_by else None
    if args.format == OutputFormat.TABLE or args.format == OutputFormat.MARKDOWN:
        fmt = args.format.value
    else:
        fmt = "json"
    warmer = start_warm_up()
    gt = load_ground_truth(gt_path)
    wait(warmer)

    def skip(path: Path, error: Exception) -> None:
        say(f"error: {error} (skipped)")

    checkpoints = evaluate_many(
        gt,
        preds,
        cfg,
        progress=sys.stderr.isatty() and not args.quiet,
        on_error=skip,
        keep_curves=bool(args.plot_dir),
    )
    text = render_batch(checkpoints, fmt, keys=keys or None, best_by=best_by)
    if args.plot:
        plot_batch(checkpoints, args.plot, keys=keys or None)
        wrote(args.plot)
    if args.plot_dir:
        from ..report.plots import plot_overlays

        written = plot_overlays([(c.label, c.result) for c in checkpoints], args.plot_dir)
        wrote(args.plot_dir, f"{len(written)} precision-recall PNGs to")
    emit(text, args.output)
    return EXIT_OK if len(checkpoints) == len(preds) else EXIT_INPUT
