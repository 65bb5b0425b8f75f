"""``kitti-eval``: the command line. Parses, loads, evaluates, prints; holds no evaluation logic.

Exit codes: 0 success, 1 bad input (unreadable, unsafe or inconsistent files), 2 usage error,
3 a gate rule failed (``kitti-eval gate``).
Data goes to stdout (or ``--output``); warnings and progress go to stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from .cli_admin import add_parser as _admin_parser
from .core.protocol import DEFAULT_CLASSES, KNOWN_CLASSES, PROTOCOLS, THRESHOLD_SETS
from .errors import ConfigError, InputError, KittiEvalError
from .report.render import OutputFormat

__all__ = ["main"]

PROG = "kitti-eval"
EXIT_OK, EXIT_INPUT, EXIT_USAGE, EXIT_GATE = 0, 1, 2, 3


def _iou_argument(text: str) -> str:
    """argparse check of an ``--iou`` value; the text itself goes to :func:`overlaps_from_overrides`."""
    from .core.protocol import parse_iou_override

    try:
        parse_iou_override(text)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 < value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


#: input-limit flag -> the environment variable it sets for this process (the loaders read it)
_LIMIT_FLAGS = {"max_input_mb": "KITTI_EVAL_MAX_UNPACKED_MB", "max_frames": "KITTI_EVAL_MAX_FRAMES"}


def _add_limit_options(p: argparse.ArgumentParser) -> None:
    limits = p.add_argument_group("input limits (untrusted input is refused past them)")
    limits.add_argument(
        "--max-input-mb",
        type=_positive,
        metavar="MB",
        help="largest pickle after decompression, and largest unpacked txt archive "
        "(default: 512, or $KITTI_EVAL_MAX_UNPACKED_MB)",
    )
    limits.add_argument(
        "--max-frames",
        type=_positive,
        metavar="N",
        help="most frames one input may hold (default: 200000, or $KITTI_EVAL_MAX_FRAMES)",
    )


@contextlib.contextmanager
def _limits_from(args: argparse.Namespace) -> Iterator[None]:
    """The limit flags given, as the environment variables every loader reads, for the command's duration."""
    before = {env: os.environ.get(env) for env in _LIMIT_FLAGS.values()}
    try:
        for flag, env in _LIMIT_FLAGS.items():
            value = getattr(args, flag, None)
            if value is not None:
                os.environ[env] = repr(value)
        yield
    finally:
        for env, value in before.items():
            if value is None:
                os.environ.pop(env, None)
            else:
                os.environ[env] = value


def _add_config_options(p: argparse.ArgumentParser) -> None:
    _add_limit_options(p)
    p.add_argument(
        "--protocol",
        choices=sorted(PROTOCOLS),
        default=None,
        help="official: the KITTI devkit's rules (default); openpcdet: what OpenPCDet prints",
    )
    p.add_argument(
        "--classes",
        default=None,
        help=f"comma-separated classes (default {','.join(DEFAULT_CLASSES)}; known: {','.join(KNOWN_CLASSES)})",
    )
    p.add_argument(
        "--iou",
        type=_iou_argument,
        action="append",
        default=[],
        metavar="CLASS[:SET]=BBOX,BEV,3D",
        help="IoU thresholds for a class, for both sets or for 'strict'/'loose' only; repeatable",
    )
    p.add_argument(
        "--ranges",
        metavar="EDGES",
        help="also evaluate by ground-plane distance from the camera, e.g. 0,30,50,inf (metres); boxes "
        "outside a range are ignored there, neither misses nor false positives",
    )
    p.add_argument(
        "--lidar-only",
        action="store_true",
        help="BEV and 3D only: no 2D boxes needed, no 2D height filter, no difficulty unless a protocol "
        "file gives occlusion/truncation limits",
    )
    p.add_argument(
        "--protocol-file",
        type=Path,
        metavar="TOML",
        help="classes, IoU thresholds, neighbour classes, difficulty limits, ranges, lidar_only, coco "
        "from a TOML file (see kitti_eval/core/protocol.py); flags given on the command line win",
    )
    p.add_argument(
        "--coco",
        action="store_true",
        help="also COCO-style AP: the mean over ten IoU thresholds (Car 0.50:0.05:0.95, Pedestrian "
        "and Cyclist 0.25:0.05:0.70)",
    )


def _output_format(text: str) -> OutputFormat:
    """An output format by name, any case (``--format`` or ``$KITTI_EVAL_FORMAT``)."""
    try:
        return OutputFormat(text.strip().lower())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"unknown format {text!r}; expected one of {', '.join(f.value for f in OutputFormat)}"
        ) from None


def _default_format() -> OutputFormat:
    raw = os.environ.get("KITTI_EVAL_FORMAT", "").strip()
    try:
        return _output_format(raw) if raw else OutputFormat.TABLE
    except argparse.ArgumentTypeError as e:
        raise ConfigError(f"KITTI_EVAL_FORMAT: {e}") from None


def _add_eval_options(p: argparse.ArgumentParser) -> None:
    _add_config_options(p)
    p.add_argument(
        "--format",
        type=_output_format,
        choices=list(OutputFormat),
        default=_default_format(),
        help="table: OpenPCDet's text; json: versioned schema; markdown: for CI summaries "
        "(default: table, or $KITTI_EVAL_FORMAT)",
    )
    p.add_argument("--curves", action="store_true", help="include the 41-point curves in the JSON output")
    p.add_argument(
        "--errors",
        action="store_true",
        help="also the error decomposition and true-positive errors ('kitti-eval errors --help'): 'errors', "
        "'errors_r11' and 'tp_errors' in the JSON, a table after the AP otherwise",
    )
    p.add_argument("--output", "-o", type=Path, help="write the result here instead of stdout")
    p.add_argument("--quiet", "-q", action="store_true", help="do not print warnings")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Exact KITTI 3D object detection evaluation (2D, BEV, 3D, AOS; R11 and R40) on a CPU.",
        epilog="Exit codes: 0 ok, 1 bad input, 2 usage error, 3 a gate rule failed ('kitti-eval gate').",
    )
    p.add_argument("--gt", type=Path, help="ground truth: a KITTI label_2 folder or an OpenPCDet infos .pkl[.gz]")
    p.add_argument(
        "--pred",
        action="append",
        metavar="PRED",
        help="predictions: a KITTI result folder (16-field txt) or an OpenPCDet result .pkl[.gz]; "
        "repeat it or give a quoted glob ('output/*/epoch_*/val/result.pkl') to evaluate many "
        "checkpoints in one process",
    )
    _add_eval_options(p)
    from .io.loaders import FORMATS

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
    sub = p.add_subparsers(dest="command", metavar="COMMAND", title="commands (each has its own --help)")
    for add in (
        _demo_parser,
        _gate_parser,
        _compare_parser,
        _frames_parser,
        _inspect_parser,
        _errors_parser,
        _describe_parser,
        _serve_parser,
        _admin_parser,
    ):
        add(sub)
    return p


def _describe_parser(sub: Any) -> argparse.ArgumentParser:
    from .io.describe import KINDS

    p = sub.add_parser(
        "describe",
        help="what a ground-truth or prediction file holds",
        description="Sniff a ground-truth or prediction file: format, frames, boxes per class, "
        "dtypes, dimension order, camera/LiDAR consistency.",
    )
    p.add_argument("file", type=Path, help="a pickle, a KITTI txt folder, or a zip/tar of one")
    p.add_argument("--kind", choices=sorted(KINDS), help="read it as ground truth or predictions (default: guess)")
    p.add_argument("--gt", type=Path, help="infos with calibration, to check prediction locations against boxes_lidar")
    p.set_defaults(run=_describe)
    return p


def _describe(args: argparse.Namespace) -> int:
    from .io.describe import describe

    _emit(describe(args.file, args.kind, args.gt), None)
    return EXIT_OK


def _serve_parser(sub: Any) -> argparse.ArgumentParser:
    """Listed for the help; :func:`main` hands everything after ``serve`` to the service's own parser."""
    return sub.add_parser(
        "serve", add_help=False, help="run the HTTP service and its web page (--help for its options)"
    )


def _serve(argv: Sequence[str]) -> int:
    try:
        from server.main import serve
    except ImportError as e:
        raise ConfigError(f"the service needs the server extra: pip install 'kitti-eval[server]' ({e})") from None
    return serve(list(argv))


def _demo(args: argparse.Namespace) -> int:
    from .io.synth import demo_paths

    gt_path, pred_path = demo_paths()
    if args.where:
        print(gt_path)
        print(pred_path)
        return EXIT_OK
    return _run(gt_path, pred_path, args)


def _demo_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "demo",
        help="evaluate the bundled demo set",
        description="Evaluate the bundled synthetic demo set (nothing is downloaded).",
    )
    _add_eval_options(p)
    p.add_argument(
        "--where",
        action="store_true",
        help="print the demo's ground-truth and prediction paths (one a line) and exit",
    )
    p.set_defaults(run=_demo)
    return p


def _config(args: argparse.Namespace):  # noqa: ANN202 - EvalConfig, imported lazily
    from .core.protocol import config_from_options, load_protocol_file

    return config_from_options(
        base=load_protocol_file(args.protocol_file) if getattr(args, "protocol_file", None) else None,
        classes=args.classes,
        protocol=args.protocol,
        iou=args.iou or (),
        ranges=getattr(args, "ranges", None),
        coco=getattr(args, "coco", False),
        lidar_only=getattr(args, "lidar_only", False),
    )


def _emit(text: str, output: Path | None) -> None:
    """A command's output: to ``--output`` when given, else to stdout."""
    if output:
        output.write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)


def _say(msg: str) -> None:
    print(f"{PROG}: {msg}", file=sys.stderr)


def _start_warm_up() -> object | None:
    """On a first run, say that the kernels compile once, and compile the evaluation kernels in another
    process while this one compiles the loader's (returns the process to wait for)."""
    from ._jit import kernels_cached, loader_cached, warm_in_background

    eval_cold, load_cold = not kernels_cached(), not loader_cached()
    if eval_cold or load_cold:
        _say("compiling the kernels once (about 7 s on two cores; later runs use numba's cache)")
    return warm_in_background() if eval_cold else None


def _wait(warmer: object | None) -> None:
    if warmer is not None:
        warmer.wait()  # type: ignore[attr-defined]


def _run(gt_path: Path, pred_path: Path, args: argparse.Namespace) -> int:
    from .core.evaluation import evaluate
    from .io.loaders import load_pair
    from .report.render import render

    config = _config(args)
    warmer = _start_warm_up()
    load_warnings: list[str] = []
    gt, dt = load_pair(
        gt_path,
        pred_path,
        gt_format=getattr(args, "gt_format", None),
        pred_format=getattr(args, "pred_format", None),
        split=getattr(args, "split", None),
        warnings=load_warnings,
    )
    _wait(warmer)
    plot_dir = getattr(args, "plot_dir", None)
    keep_curves = args.curves or bool(plot_dir)
    extra: dict[str, Any] | None = None
    if args.errors:
        from .analysis.decomposition import errors_document, evaluate_with_errors, render_errors

        result, decomposition = evaluate_with_errors(gt, dt, config, keep_curves=keep_curves)
        extra = errors_document(decomposition, full=False)
    else:
        result = evaluate(gt, dt, config, keep_curves=keep_curves)
    if plot_dir:
        from .report.plots import plot_pr_curves

        plot_pr_curves(result, plot_dir)
    text = render(result, args.format, include_curves=args.curves, extra=extra)
    if args.errors and args.format is not OutputFormat.JSON:
        text += "\n" + render_errors(decomposition, args.format.value)
    if not args.quiet:
        for w in [*load_warnings, *result.warnings]:
            _say(f"warning: {w}")
    _emit(text, args.output)
    return EXIT_OK


def _run_sharded(args: argparse.Namespace) -> int:
    from .analysis.batch import expand_predictions
    from .analysis.cluster import cluster_mapper, progress_mapper
    from .analysis.sharded import evaluate_sharded
    from .report.render import render

    if not args.sharded:
        raise ConfigError("--cluster evaluates a set given in shards: add --sharded")
    if args.errors:
        raise ConfigError("--errors works with one --gt and one --pred, not with --sharded")
    if args.split or args.plot or args.plot_dir:
        raise ConfigError("--split, --plot and --plot-dir do not work with --sharded")
    config = _config(args)
    gts = expand_predictions([args.gt])
    preds = expand_predictions(args.pred)
    show = sys.stderr.isatty() and not args.quiet
    context = cluster_mapper(args.cluster, progress=show) if args.cluster else contextlib.nullcontext(None)
    with context as mapper:
        result = evaluate_sharded(
            gts,
            preds,
            config,
            gt_format=args.gt_format,
            pred_format=args.pred_format,
            keep_curves=args.curves,
            mapper=mapper or progress_mapper(show),
            source=(str(args.gt), ", ".join(str(p) for p in args.pred)),
        )
    if not args.quiet:
        for w in result.warnings:
            _say(f"warning: {w}")
    _emit(render(result, args.format, include_curves=args.curves), args.output)
    return EXIT_OK


def _gate_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "gate",
        help="check AP rules on a result (exit 3 when a rule fails)",
        description="Check AP rules on a result: floors, maximum drops against a baseline, required classes. "
        "Exit 0 when every rule passes, 3 when one fails, 1 on bad input, 2 on usage errors.",
        epilog="Values are named Class/metric/difficulty[/R40|R11[/strict|loose]] (default R40, strict). "
        "A rule on a value that is null (not evaluated) fails.",
    )
    src = p.add_argument_group("the result to gate: a saved JSON result, or ground truth and predictions")
    src.add_argument("--result", type=Path, help="a JSON result written by 'kitti-eval --format json'")
    src.add_argument("--gt", type=Path, help="ground truth (evaluated with --pred)")
    src.add_argument("--pred", type=Path, help="predictions to evaluate")
    src.add_argument(
        "--sharded",
        action="store_true",
        help="--gt, --pred and a --baseline given as predictions are quoted globs of shards of one set each",
    )
    _add_config_options(p)
    rules = p.add_argument_group("rules")
    rules.add_argument(
        "--min",
        "--rule",
        dest="floors",
        action="append",
        default=[],
        metavar="RULE",
        help="a bound such as 'Car/3d/moderate/R40 >= 78.5' (any of >=, >, <=, <), or on an error type of the "
        "decomposition, 'Car/3d/moderate/localization <= 5' (then --gt/--pred are evaluated with it); repeatable",
    )
    rules.add_argument(
        "--max-drop",
        action="append",
        default=[],
        metavar="[VALUE=]N",
        help="largest allowed drop against --baseline, in AP points: N for every value, or "
        "Car/3d/moderate=N for one; repeatable",
    )
    rules.add_argument(
        "--require-class",
        action="append",
        default=[],
        metavar="CLASS",
        help="fail unless this class was evaluated; repeatable",
    )
    rules.add_argument("--rules", type=Path, help="rules from a TOML file (floor, max_drop, require_classes)")
    p.add_argument(
        "--baseline", type=Path, help="the result to compare with: a JSON result, or predictions evaluated against --gt"
    )
    sig = p.add_argument_group("significance")
    sig.add_argument(
        "--significant",
        action="store_true",
        help="fail a drop only if a paired bootstrap over frames says it is significant (95%%); "
        "needs --gt, --pred and --baseline as predictions",
    )
    sig.add_argument("--bootstrap", type=int, default=1000, metavar="N", help="resamples for --significant")
    sig.add_argument("--seed", type=int, default=0, help="seed of the resampling (default 0)")
    out = p.add_argument_group("reports")
    out.add_argument("--markdown", type=Path, help="also write the verdict as Markdown (CI job summaries)")
    out.add_argument("--junit", type=Path, help="also write the verdict as JUnit XML")
    out.add_argument("--show-passed", action="store_true", help="list passing checks too")
    p.set_defaults(run=_gate)
    return p


def _compare_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "compare",
        help="per-value differences between two results",
        description="Per-value differences B - A between two results, with paired bootstrap intervals over "
        "frames when both are predictions (--gt) and --bootstrap N is given.",
    )
    p.add_argument("a", type=Path, help="result A: a JSON result, or predictions (with --gt)")
    p.add_argument("b", type=Path, help="result B: a JSON result, or predictions (with --gt)")
    p.add_argument("--gt", type=Path, help="ground truth, to evaluate predictions given as A or B")
    p.add_argument("--bootstrap", type=int, default=0, metavar="N", help="paired bootstrap resamples (e.g. 1000)")
    p.add_argument("--seed", type=int, default=0, help="seed of the resampling (default 0)")
    p.add_argument("--all", action="store_true", help="every value, not only R40 with the strict thresholds")
    p.add_argument(
        "--errors",
        action="store_true",
        help="which error types changed: the error decomposition of A and B (kitti-eval errors) side by side",
    )
    p.add_argument(
        "--sharded",
        action="store_true",
        help="A, B and --gt are quoted globs of shards of one set each, evaluated (and bootstrapped) part by part",
    )
    p.add_argument("--format", choices=["table", "json", "markdown"], default="table")
    p.add_argument("--output", "-o", type=Path, help="write the comparison here instead of stdout")
    _add_config_options(p)
    p.set_defaults(run=_compare)
    return p


def _compare(args: argparse.Namespace) -> int:
    from .analysis.bootstrap import paired_bootstrap
    from .analysis.compare import compare_documents, render_comparison

    if args.bootstrap < 0:
        raise ConfigError("--bootstrap must be >= 0")
    is_json = [p.suffix.lower() == ".json" for p in (args.a, args.b)]
    intervals = None
    if args.sharded:
        if args.gt is None or any(is_json) or args.errors:
            raise ConfigError("--sharded compares predictions given in shards: A, B and --gt as globs, no --errors")
        from .analysis.batch import expand_predictions
        from .analysis.sharded import evaluate_sharded, paired_bootstrap_sharded

        gts, preds_a, preds_b = (expand_predictions([x]) for x in (args.gt, args.a, args.b))
        if args.bootstrap:
            res_a, res_b, intervals = paired_bootstrap_sharded(
                gts, preds_a, preds_b, _config(args), resamples=args.bootstrap, seed=args.seed
            )
        else:
            res_a, res_b = (evaluate_sharded(gts, p, _config(args)) for p in (preds_a, preds_b))
        doc_a, doc_b = res_a.to_dict(), res_b.to_dict()
    elif args.bootstrap:
        if any(is_json) or args.gt is None:
            raise ConfigError("--bootstrap needs predictions for both A and B, and --gt")
        from .io.loaders import load_detections, load_ground_truth

        gt = load_ground_truth(args.gt)
        res_a, res_b, intervals = paired_bootstrap(
            gt,
            load_detections(args.a),
            load_detections(args.b),
            _config(args),
            resamples=args.bootstrap,
            seed=args.seed,
        )
        doc_a, doc_b = res_a.to_dict(), res_b.to_dict()
    else:
        doc_a, doc_b = (
            _read_result_json(p) if j else _evaluate_doc(args, p, errors=args.errors)
            for p, j in zip((args.a, args.b), is_json)
        )
    if args.errors:
        if args.bootstrap:
            raise ConfigError("--errors and --bootstrap are not given together")
        lacking = [str(p) for p, d in zip((args.a, args.b), (doc_a, doc_b)) if "errors" not in d]
        if lacking:
            raise InputError(f"no error decomposition in {', '.join(lacking)}: save it with --errors")
    text = render_comparison(
        compare_documents(
            doc_a, doc_b, intervals, args.bootstrap, args.seed if args.bootstrap else None, errors_only=args.errors
        ),
        args.format,
        every_value=args.all,
    )
    _emit(text, args.output)
    return EXIT_OK


def _evaluate_doc(args: argparse.Namespace, pred: Path, *, errors: bool = False) -> dict:
    """The result document of ``pred`` against ``--gt`` (with ``errors``: and its error decomposition)."""
    from .core.evaluation import evaluate
    from .io.loaders import load_pair

    if args.gt is None:
        raise ConfigError(f"{pred} is not a JSON result; evaluating it needs --gt")
    gt, dt = load_pair(args.gt, pred)
    if not errors:
        return evaluate(gt, dt, _config(args)).to_dict()
    from .analysis.decomposition import errors_document, evaluate_with_errors

    result, decomposition = evaluate_with_errors(gt, dt, _config(args))
    return {**result.to_dict(), **errors_document(decomposition, full=False)}


def _add_slot_options(p: argparse.ArgumentParser, metrics: list[str]) -> None:
    """Which matching to look at: class, metric, difficulty and IoU threshold set."""
    p.add_argument("--class", dest="cls", default="Car", help="the class (default Car)")
    p.add_argument("--metric", default="3d", choices=metrics, help="default 3d")
    p.add_argument("--difficulty", default="moderate", choices=["easy", "moderate", "hard"])
    p.add_argument("--set", dest="oset", default="strict", choices=list(THRESHOLD_SETS), help="IoU threshold set")


def _frames_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "frames",
        help="hits, false positives and misses per frame",
        description="True positives, false positives and misses of every frame for one class, metric and "
        "difficulty, from the same matching as the AP; --worst N lists the frames with most errors.",
    )
    p.add_argument("--gt", required=True, type=Path, help="ground truth (a quoted glob with --sharded)")
    p.add_argument(
        "--pred", required=True, action="append", help="predictions (with --sharded: globs or repeated, the shards)"
    )
    p.add_argument("--sharded", action="store_true", help="--gt and --pred are shards of one set, read part by part")
    _add_slot_options(p, ["bbox", "bev", "3d"])
    p.add_argument(
        "--score-threshold",
        type=float,
        default=0.0,
        help="count detections scoring at least this (default 0: every detection)",
    )
    p.add_argument("--worst", type=int, metavar="N", help="only the N frames with most errors (FP + FN)")
    p.add_argument("--format", choices=["table", "csv", "json"], default="table")
    p.add_argument("--output", "-o", type=Path)
    _add_config_options(p)
    p.set_defaults(run=_frames)
    return p


def _frames(args: argparse.Namespace) -> int:
    from .analysis.diagnostics import frame_stats, render_frames
    from .io.loaders import load_pair

    if args.worst is not None and args.worst < 1:
        raise ConfigError("--worst must be >= 1")
    slot = dict(
        cls=args.cls,
        metric=args.metric,
        difficulty=args.difficulty,
        oset=args.oset,
        score_threshold=args.score_threshold,
    )
    if args.sharded:
        from .analysis.batch import expand_predictions
        from .analysis.sharded import frame_stats_sharded

        stats = frame_stats_sharded(expand_predictions([args.gt]), expand_predictions(args.pred), _config(args), **slot)
    else:
        if len(args.pred) > 1:
            raise ConfigError("one --pred, or --sharded for a set in many files")
        stats = frame_stats(*load_pair(args.gt, Path(args.pred[0])), _config(args), **slot)
    text = render_frames(stats, args.format, worst=args.worst)
    _emit(text, args.output)
    return EXIT_OK


def _errors_parser(sub: Any) -> argparse.ArgumentParser:
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
    _add_config_options(p)
    p.set_defaults(run=_errors)
    return p


def _errors(args: argparse.Namespace) -> int:
    from .analysis.decomposition import decompose_plan, render_errors
    from .core.evaluation import plan_evaluation
    from .io.loaders import load_pair

    config = _config(args)
    warmer = _start_warm_up()
    load_warnings: list[str] = []
    gt, dt = load_pair(args.gt, args.pred, warnings=load_warnings)
    _wait(warmer)
    plan = plan_evaluation(gt, dt, config)
    text = render_errors(decompose_plan(plan, oset=args.oset), args.format, recall=args.recall)
    if not args.quiet:
        for w in [*load_warnings, *plan.warnings]:
            _say(f"warning: {w}")
    _emit(text, args.output)
    return EXIT_OK


def _inspect_parser(sub: Any) -> argparse.ArgumentParser:
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
    _add_slot_options(p, ["bbox", "bev", "3d", "aos"])
    p.add_argument(
        "--score-threshold",
        type=float,
        default=None,
        help="detections scoring below this take no part (default: all take part)",
    )
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("--output", "-o", type=Path)
    _add_config_options(p)
    p.set_defaults(run=_inspect)
    return p


def _inspect(args: argparse.Namespace) -> int:
    from .analysis.inspection import inspect_frame, inspection_json, model_name, render_inspection, unique_names
    from .io.loaders import load_detections, load_ground_truth_and_calibs

    if args.name and len(args.name) != len(args.pred):
        raise ConfigError(f"--name given {len(args.name)} times for {len(args.pred)} --pred")
    names = args.name or unique_names([model_name(p) for p in args.pred])  # inspect_frame refuses repeats
    gt, calibs = load_ground_truth_and_calibs(args.gt)
    models = [(name, load_detections(path, calibs=calibs, keep_lidar=True)) for name, path in zip(names, args.pred)]
    report = inspect_frame(
        gt,
        models,
        args.frame,
        _config(args),
        cls=args.cls,
        metric=args.metric,
        difficulty=args.difficulty,
        oset=args.oset,
        score_threshold=args.score_threshold,
    )
    text = inspection_json(report) if args.format == "json" else render_inspection(report)
    _emit(text, args.output)
    return EXIT_OK


def _read_result_json(path: Path) -> dict:
    import json

    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such file", source=str(path)) from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"not a JSON result: {e}", source=str(path)) from None
    if not isinstance(doc, dict) or doc.get("schema_version") != 1 or not isinstance(doc.get("ap"), dict):
        raise InputError("not a kitti-eval JSON result (schema_version 1 with an 'ap' table)", source=str(path))
    return doc


def _gate(args: argparse.Namespace) -> int:
    from .analysis.gate import (
        render_junit,
        render_verdict,
        render_verdict_markdown,
        rules_from_options,
        rules_from_toml,
        run_gate,
    )

    rules = rules_from_options(
        args.floors,
        args.max_drop,
        args.require_class,
        baseline=bool(args.baseline),
        also=rules_from_toml(args.rules) if args.rules else None,
    )
    if args.result and (args.gt or args.pred):
        raise ConfigError("give either --result or --gt with --pred, not both")
    if not args.result and not (args.gt and args.pred):
        raise ConfigError("give the result to gate: --result R.json, or --gt and --pred")

    intervals = None
    if args.sharded:
        current, baseline, intervals = _gate_sharded(args, rules.needs_errors)
    elif args.significant:
        if not (args.gt and args.pred and args.baseline) or args.baseline.suffix.lower() == ".json":
            raise ConfigError("--significant needs --gt, --pred and a --baseline given as predictions")
        from .analysis.bootstrap import paired_bootstrap
        from .io.loaders import load_detections, load_ground_truth

        res_base, res_now, intervals = paired_bootstrap(
            load_ground_truth(args.gt),
            load_detections(args.baseline),
            load_detections(args.pred),
            _config(args),
            resamples=args.bootstrap,
            seed=args.seed,
        )
        current, baseline = res_now.to_dict(), res_base.to_dict()
    else:
        current = (
            _read_result_json(args.result) if args.result else _evaluate_doc(args, args.pred, errors=rules.needs_errors)
        )
        baseline = None
        if args.baseline:
            baseline = (
                _read_result_json(args.baseline)
                if args.baseline.suffix.lower() == ".json"
                else _evaluate_doc(args, args.baseline)
            )
    verdict = run_gate(current, rules, baseline, intervals)
    sys.stdout.write(render_verdict(verdict, show_passed=args.show_passed))
    if args.markdown:
        args.markdown.write_text(render_verdict_markdown(verdict), encoding="utf-8")
    if args.junit:
        args.junit.write_text(render_junit(verdict), encoding="utf-8")
    return EXIT_OK if verdict.passed else EXIT_GATE


def _gate_sharded(args: argparse.Namespace, needs_errors: bool) -> tuple[dict, dict | None, dict | None]:
    """The documents (and with --significant the intervals) a gate reads, for sets given in shards."""
    from .analysis.batch import expand_predictions
    from .analysis.sharded import evaluate_sharded, paired_bootstrap_sharded

    if not (args.gt and args.pred) or args.result:
        raise ConfigError("--sharded gates predictions given in shards: --gt and --pred as globs")
    if needs_errors:
        raise ConfigError("rules on error types need the set in one piece (the decomposition is not sharded)")
    baseline_is_json = args.baseline is not None and args.baseline.suffix.lower() == ".json"
    if args.significant and (args.baseline is None or baseline_is_json):
        raise ConfigError("--significant needs a --baseline given as predictions")
    gts, preds = expand_predictions([args.gt]), expand_predictions([args.pred])
    if args.significant:
        base, now, intervals = paired_bootstrap_sharded(
            gts, expand_predictions([args.baseline]), preds, _config(args), resamples=args.bootstrap, seed=args.seed
        )
        return now.to_dict(), base.to_dict(), intervals
    current = evaluate_sharded(gts, preds, _config(args)).to_dict()
    if args.baseline is None:
        return current, None, None
    if baseline_is_json:
        return current, _read_result_json(args.baseline), None
    return current, evaluate_sharded(gts, expand_predictions([args.baseline]), _config(args)).to_dict(), None


def _run_many(gt_path: Path, preds: list[Path], args: argparse.Namespace) -> int:
    from .analysis.batch import evaluate_many, plot_batch, render_batch
    from .analysis.gate import ValueKey
    from .io.loaders import load_ground_truth

    config = _config(args)
    keys = [ValueKey.parse(k) for k in args.value]
    best_by = ValueKey.parse(args.best_by) if args.best_by else None
    if args.format == OutputFormat.TABLE or args.format == OutputFormat.MARKDOWN:
        fmt = args.format.value
    else:
        fmt = "json"
    warmer = _start_warm_up()
    gt = load_ground_truth(gt_path)
    _wait(warmer)

    def skip(path: Path, error: Exception) -> None:
        _say(f"error: {error} (skipped)")

    checkpoints = evaluate_many(
        gt,
        preds,
        config,
        progress=sys.stderr.isatty() and not args.quiet,
        on_error=skip,
        keep_curves=bool(args.plot_dir),
    )
    text = render_batch(checkpoints, fmt, keys=keys or None, best_by=best_by)
    if args.plot:
        plot_batch(checkpoints, args.plot, keys=keys or None)
    if args.plot_dir:
        from .report.plots import plot_overlays

        plot_overlays([(c.label, c.result) for c in checkpoints], args.plot_dir)
    _emit(text, args.output)
    return EXIT_OK if len(checkpoints) == len(preds) else EXIT_INPUT


def _command(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if args.command is not None:
        return int(args.run(args))
    if args.gt is None or not args.pred:
        parser.error("the following arguments are required: --gt, --pred (or a command)")
    from .analysis.batch import expand_predictions

    if args.sharded or args.cluster:
        return _run_sharded(args)
    preds = expand_predictions(args.pred)
    if len(preds) == 1 and not args.plot and not (args.plot_dir and len(args.pred) > 1):
        return _run(args.gt, preds[0], args)
    if args.gt_format or args.pred_format or args.split or args.errors:
        raise ConfigError("--gt-format, --pred-format, --split and --errors work with one --pred only")
    return _run_many(args.gt, preds, args)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv[:1] == ["serve"]:
            return _serve(argv[1:])
        parser = _parser()
        args = parser.parse_args(argv)
        with _limits_from(args):
            return _command(parser, args)
    except SystemExit as e:  # argparse: usage errors exit 2, --help exits 0
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    except ConfigError as e:
        _say(f"error: {e}")
        return EXIT_USAGE
    except InputError as e:
        _say(f"error: {e}")
        return EXIT_INPUT
    except KittiEvalError as e:
        _say(f"error: {e}")
        return EXIT_INPUT
    except OSError as e:
        _say(f"error: {e.strerror or e}: {e.filename or ''}".rstrip(": "))
        return EXIT_INPUT
    except KeyboardInterrupt:
        return 130


def entry() -> None:
    """The console script: :func:`main`, then leave without tearing the interpreter down.

    Everything the command writes is flushed or closed by then; skipping the teardown of numba, llvmlite
    and the loaded arrays saves about 0.15 s on every run.
    """
    code = main()
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed pipe: nothing more can be said
        code = code or EXIT_INPUT
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
