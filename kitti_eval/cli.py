"""``kitti-eval``: the command line. Parses, loads, evaluates, prints; holds no evaluation logic.

Exit codes: 0 success, 1 bad input (unreadable, unsafe or inconsistent files), 2 usage error.
Data goes to stdout (or ``--output``); warnings and progress go to stderr.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from .errors import ConfigError, InputError, KittiEvalError
from .formats import OutputFormat
from .protocol import DEFAULT_CLASSES, KNOWN_CLASSES, PROTOCOLS, THRESHOLD_SETS

__all__ = ["main"]

PROG = "kitti-eval"
EXIT_OK, EXIT_INPUT, EXIT_USAGE = 0, 1, 2


def _parse_iou(text: str) -> tuple[str, str | None, tuple[float, float, float]]:
    """``Car=0.7,0.6,0.6`` (both threshold sets) or ``Car:loose=0.7,0.5,0.5``."""
    try:
        key, values = text.split("=", 1)
        cls, _, oset = key.partition(":")
        triple = tuple(float(v) for v in values.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected CLASS[:SET]=BBOX,BEV,3D, got {text!r}") from None
    if len(triple) != 3 or not cls:
        raise argparse.ArgumentTypeError(f"expected CLASS[:SET]=BBOX,BEV,3D, got {text!r}")
    if oset and oset not in THRESHOLD_SETS:
        raise argparse.ArgumentTypeError(f"threshold set must be one of {', '.join(THRESHOLD_SETS)}, got {oset!r}")
    return cls, oset or None, triple  # type: ignore[return-value]


def _add_eval_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--protocol", choices=sorted(PROTOCOLS), default="official",
                   help="official: the KITTI devkit's rules (default); openpcdet: what OpenPCDet prints")
    p.add_argument("--format", type=OutputFormat, choices=list(OutputFormat),
                   default=OutputFormat(os.environ.get("KITTI_EVAL_FORMAT", "table")),
                   help="table: OpenPCDet's text; json: versioned schema; markdown: for CI summaries "
                        "(default: table, or $KITTI_EVAL_FORMAT)")
    p.add_argument("--classes", default=",".join(DEFAULT_CLASSES),
                   help=f"comma-separated classes (default {','.join(DEFAULT_CLASSES)}; "
                        f"known: {','.join(KNOWN_CLASSES)})")
    p.add_argument("--iou", type=_parse_iou, action="append", default=[], metavar="CLASS[:SET]=BBOX,BEV,3D",
                   help="IoU thresholds for a class, for both sets or for 'strict'/'loose' only; repeatable")
    p.add_argument("--curves", action="store_true", help="include the 41-point curves in the JSON output")
    p.add_argument("--output", "-o", type=Path, help="write the result here instead of stdout")
    p.add_argument("--quiet", "-q", action="store_true", help="do not print warnings")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Exact KITTI 3D object detection evaluation (2D, BEV, 3D, AOS; R11 and R40) on a CPU.",
        epilog="Commands: 'kitti-eval demo' evaluates the bundled demo set. "
               "Exit codes: 0 ok, 1 bad input, 2 usage.")
    p.add_argument("--gt", required=True, type=Path,
                   help="ground truth: a KITTI label_2 folder or an OpenPCDet infos .pkl[.gz]")
    p.add_argument("--pred", required=True, type=Path,
                   help="predictions: a KITTI result folder (16-field txt) or an OpenPCDet result .pkl[.gz]")
    _add_eval_options(p)
    return p


def _demo_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=f"{PROG} demo",
                                description="Evaluate the bundled synthetic demo set (nothing is downloaded).")
    _add_eval_options(p)
    return p


def _config(args: argparse.Namespace):  # noqa: ANN202 - EvalConfig, imported lazily
    from .protocol import EvalConfig

    classes = tuple(c.strip() for c in args.classes.split(",") if c.strip())
    overlaps: dict[str, dict[str, tuple[float, float, float]]] = {}
    for cls, oset, triple in args.iou:
        for s in ([oset] if oset else THRESHOLD_SETS):
            overlaps.setdefault(cls, {})[s] = triple
    return EvalConfig(classes=classes, protocol=PROTOCOLS[args.protocol], overlaps=overlaps)


def _say(msg: str) -> None:
    print(f"{PROG}: {msg}", file=sys.stderr)


def _run(gt_path: Path, pred_path: Path, args: argparse.Namespace) -> int:
    from ._jit import kernels_cached
    from .evaluation import evaluate
    from .formats import render
    from .loaders import load_detections, load_ground_truth

    config = _config(args)
    gt = load_ground_truth(gt_path)
    dt = load_detections(pred_path)
    if not kernels_cached():
        _say("compiling the evaluation kernels once (takes a few seconds; later runs use numba's cache)")
    result = evaluate(gt, dt, config, keep_curves=args.curves)
    text = render(result, args.format, include_curves=args.curves)
    if not args.quiet:
        for w in result.warnings:
            _say(f"warning: {w}")
    if args.output:
        args.output.write_text(text)
    else:
        sys.stdout.write(text)
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv and argv[0] == "demo":
            args = _demo_parser().parse_args(argv[1:])
            from .synth import demo_paths

            gt_path, pred_path = demo_paths()
            return _run(gt_path, pred_path, args)
        args = _parser().parse_args(argv)
        return _run(args.gt, args.pred, args)
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


if __name__ == "__main__":
    sys.exit(main())
