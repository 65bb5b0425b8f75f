"""What the commands share: exit codes, the option groups several commands take, the evaluation
configuration they build from them, and how a command writes its output and warnings."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

from ..analysis.frame_question import ASKED
from ..core.protocol import DEFAULT_CLASSES, DIFFICULTIES, KNOWN_CLASSES, PROTOCOLS, THRESHOLD_SETS
from ..errors import ConfigError, InputError
from ..report.render import OutputFormat

PROG = "kitti-eval"
EXIT_OK, EXIT_INPUT, EXIT_USAGE, EXIT_GATE = 0, 1, 2, 3
#: a service's client (kitti-eval submit, --service): over a benchmark's quota; the service could not be reached
EXIT_QUOTA, EXIT_UNREACHABLE = 4, 5


def _iou_argument(text: str) -> str:
    """argparse check of an ``--iou`` value; the text itself goes to :func:`overlaps_from_overrides`."""
    from ..core.protocol import parse_iou_override

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
_LIMIT_FLAGS = {
    "max_input_mb": "KITTI_EVAL_MAX_UNPACKED_MB",
    "max_frames": "KITTI_EVAL_MAX_FRAMES",
    "max_boxes_per_frame": "KITTI_EVAL_MAX_BOXES_PER_FRAME",
    "max_boxes": "KITTI_EVAL_MAX_BOXES",
    "max_frame_pairs": "KITTI_EVAL_MAX_FRAME_PAIRS",
    "max_pairs": "KITTI_EVAL_MAX_PAIRS",
}


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
    limits.add_argument(
        "--max-boxes-per-frame",
        type=_positive,
        metavar="N",
        help="most boxes one frame of an input may hold (default: 10000, or $KITTI_EVAL_MAX_BOXES_PER_FRAME)",
    )
    limits.add_argument(
        "--max-boxes",
        type=_positive,
        metavar="N",
        help="most boxes one input may hold (default: 5000000, or $KITTI_EVAL_MAX_BOXES)",
    )
    limits.add_argument(
        "--max-frame-pairs",
        type=_positive,
        metavar="N",
        help="most detection x ground-truth overlaps of one frame (default: 4000000, or $KITTI_EVAL_MAX_FRAME_PAIRS)",
    )
    limits.add_argument(
        "--max-pairs",
        type=_positive,
        metavar="N",
        help="most detection x ground-truth overlaps of one evaluation (default: 100000000, or $KITTI_EVAL_MAX_PAIRS)",
    )


@contextlib.contextmanager
def limits_from(args: argparse.Namespace) -> Iterator[None]:
    """The limit flags given, as the environment variables every loader reads, for the command's duration."""
    from ..core.budget import set_by_flags

    before = {env: os.environ.get(env) for env in _LIMIT_FLAGS.values()}
    given: dict[str, str] = {}
    try:
        for flag, env in _LIMIT_FLAGS.items():
            value = getattr(args, flag, None)
            if value is not None:
                os.environ[env] = repr(value)
                given[env] = "--" + flag.replace("_", "-")
        with set_by_flags(given):
            yield
    finally:
        for env, value in before.items():
            if value is None:
                os.environ.pop(env, None)
            else:
                os.environ[env] = value


def add_config_options(p: argparse.ArgumentParser) -> None:
    """The input limits and everything :func:`config` reads: protocol, classes, IoU, ranges, ..."""
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


def add_eval_options(p: argparse.ArgumentParser) -> None:
    """What an evaluation printing an AP table takes (the main job and ``demo``)."""
    add_config_options(p)
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


def add_slot_options(p: argparse.ArgumentParser, metrics: list[str]) -> None:
    """Which matching to look at: class, metric, difficulty and IoU threshold set."""
    p.add_argument("--class", dest="cls", default=ASKED.cls, help=f"the class (default {ASKED.cls})")
    p.add_argument("--metric", default=ASKED.metric, choices=metrics, help=f"default {ASKED.metric}")
    p.add_argument("--difficulty", default=ASKED.difficulty, choices=list(DIFFICULTIES))
    p.add_argument("--set", dest="oset", default=ASKED.oset, choices=list(THRESHOLD_SETS), help="IoU threshold set")


def say_defaults(parser: argparse.ArgumentParser) -> None:
    """Every option's help states its default (``frames --difficulty``: moderate), unless it already does: the
    default is appended to the help of every option of ``parser`` and its subcommands that has one."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in dict.fromkeys(action.choices.values()):
                say_defaults(subparser)
        elif action.option_strings and action.help != argparse.SUPPRESS and has_default(action):
            if "default" not in (action.help or ""):
                action.help = f"{action.help} (default: %(default)s)" if action.help else "default: %(default)s"


def has_default(action: argparse.Action) -> bool:
    """Whether an option has a default worth stating (not unset, off or empty)."""
    return action.default not in (None, False, [], "", argparse.SUPPRESS) and action.nargs != 0


def config(args: argparse.Namespace):  # noqa: ANN201 - EvalConfig, imported lazily
    """The evaluation configuration of a command's options (see :func:`add_config_options`)."""
    from ..core.protocol import config_from_options, load_protocol_file

    return config_from_options(
        base=load_protocol_file(args.protocol_file) if getattr(args, "protocol_file", None) else None,
        classes=args.classes,
        protocol=args.protocol,
        iou=args.iou or (),
        ranges=getattr(args, "ranges", None),
        coco=getattr(args, "coco", False),
        lidar_only=getattr(args, "lidar_only", False),
    )


def emit(text: str, output: Path | None) -> None:
    """A command's output: to ``--output`` when given (and said on stderr), else to stdout."""
    if output:
        output.write_text(text, encoding="utf-8")
        wrote(output)
    else:
        sys.stdout.write(text)


def wrote(path: Path | str, what: str = "") -> None:
    """Say on stderr where a command wrote a file (every command that writes one names it)."""
    say(f"wrote {what + ' ' if what else ''}{path}")


def say(msg: str) -> None:
    print(f"{PROG}: {msg}", file=sys.stderr)


def start_warm_up(*, decomposition: bool = False) -> object | None:
    """On a first run, say that the kernels compile once, and compile the evaluation kernels in another
    process while this one compiles the loader's (returns the process to wait for). ``decomposition``: the
    command runs the error decomposition too, whose kernels compile on their first use. Where numba's cache has
    no writable place, nothing is started (what another process compiled would not be kept): the kernels are
    compiled here, in memory, and the one warning saying so is this command's ``kitti-eval: warning:`` line."""
    from .._jit import decomposition_cached, kernels_cached, loader_cached, warm_in_background
    from ..core.kernel_cache import route_warnings, writable_cache

    route_warnings(lambda message: say(f"warning: {message}"))
    eval_cold, load_cold = not kernels_cached(), not loader_cached()
    decomposition_cold = decomposition and not decomposition_cached()
    if not (eval_cold or load_cold or decomposition_cold):
        return None  # a warm run: no look for a writable cache folder
    if writable_cache() is None:  # nowhere to keep them: compiled here, in memory (the warning says so)
        return None
    if eval_cold or load_cold:
        say("compiling the kernels once (later runs use numba's cache)")
    if decomposition_cold:
        say("compiling the error decomposition's kernels once (later runs use numba's cache)")
    # the scan too when it is not cached: a run that reads only txt files never compiles it itself, and would
    # otherwise find it missing and say "compiling" on every run
    return warm_in_background(loader=load_cold) if eval_cold or load_cold else None


def wait(warmer: object | None) -> None:
    if warmer is not None:
        warmer.wait()  # type: ignore[attr-defined]


def read_result_json(path: Path) -> dict:
    """A result document saved by ``kitti-eval --format json``."""
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


def evaluate_doc(args: argparse.Namespace, pred: Path, *, errors: bool = False) -> dict:
    """The result document of ``pred`` against ``--gt`` (with ``errors``: and its error decomposition)."""
    from ..core.evaluation import evaluate
    from ..io.loaders import load_pair

    if args.gt is None:
        raise ConfigError(f"{pred} is not a JSON result; evaluating it needs --gt")
    gt, dt = load_pair(args.gt, pred)
    if not errors:
        return evaluate(gt, dt, config(args)).to_dict()
    from ..analysis.decomposition import errors_document, evaluate_with_errors

    result, decomposition = evaluate_with_errors(gt, dt, config(args))
    return {**result.to_dict(), **errors_document(decomposition, full=False)}


def several_gt(gts: Sequence[Path]) -> ConfigError:
    """The error for several ``--gt`` files without ``--sharded``."""
    shown = ", ".join(str(g) for g in gts[:3]) + (", ..." if len(gts) > 3 else "")
    return ConfigError(
        f"{len(gts)} --gt files given ({shown}): several ground-truth files are the shards of one set, add "
        "--sharded; to evaluate many checkpoints give one --gt and several --pred"
    )
