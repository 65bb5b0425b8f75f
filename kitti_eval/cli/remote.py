"""The commands' side of the service's client (:mod:`kitti_eval.client`): the ``--service`` options, the main job
and ``gate`` done by a service, and what a refusal of the service exits with.

Exit codes besides the CLI's own: 4 over a benchmark's quota (the message says when the next submission is
accepted), 5 the service could not be reached (no answer, or only "away" answers, within ``--retry-for``).
A file the service refuses exits 1, as a file refused here does; any other refusal of the request (no token,
a token without the right, an unknown ground truth or benchmark, a closed benchmark) exits 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ConfigError, QuotaExceeded, ServiceError, ServiceUnreachable, SubmissionRefused
from .common import EXIT_INPUT, EXIT_OK, EXIT_QUOTA, EXIT_UNREACHABLE, EXIT_USAGE, emit, say

if TYPE_CHECKING:
    from ..client import Client

__all__ = [
    "add_connection_arguments",
    "add_service_arguments",
    "client_of",
    "service_of",
    "quota_left",
    "exit_code",
    "report",
    "run_evaluation",
    "run_gate",
]

#: how long a request is sent again while the service is away, unless --retry-for says
RETRY_FOR_S = 300.0


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def _label(text: str) -> str:
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return text


def add_connection_arguments(group: Any, *, required: bool = False, saved: bool = False) -> None:
    """``--service``, how long to try it and ``--allow-http`` (every command that talks to a service).
    ``saved``: ``--service`` may be left out when ``kitti-eval login`` saved a token for one service only."""
    if saved:
        where = " (default: the one service 'kitti-eval login' saved a token for)"
    else:
        where = "" if required else " (default: none, evaluate here)"
    group.add_argument(
        "--service",
        metavar="URL",
        required=required,
        help="the service, http(s)://HOST[:PORT]; the token is $KITTI_EVAL_TOKEN, else the one 'kitti-eval "
        "login' saved for it" + where,
    )
    group.add_argument(
        "--retry-for",
        type=_seconds,
        default=RETRY_FOR_S,
        metavar="S",
        help="how long to send a request again while the service is away (no answer, restarting, 503), with "
        f"backoff and jitter; exit 5 past it (default: {RETRY_FOR_S:g})",
    )
    group.add_argument(
        "--allow-http",
        action="store_true",
        help="send the token over plain http to a host other than this machine (a trusted network only; "
        "$KITTI_EVAL_ALLOW_HTTP=1 says the same; default: refused, use https)",
    )


def service_of(args: argparse.Namespace) -> str:
    """The service a command talks to: ``--service``, else the one service ``kitti-eval login`` saved a token
    for (set on ``args`` for the command's sentences)."""
    if getattr(args, "service", None):
        return str(args.service)
    from ..client import saved_services

    saved = saved_services()
    if len(saved) != 1:
        known = f" (tokens are saved for {', '.join(saved)})" if saved else ""
        raise ConfigError(
            f"which service? give --service URL{known}, or save a token once with 'kitti-eval login --service URL'"
        )
    args.service = saved[0]
    return args.service


def add_service_arguments(p: argparse.ArgumentParser) -> None:
    """The main job's and ``gate``'s options for an evaluation done by a service."""
    group = p.add_argument_group(
        "evaluated by a service (--gt names a ground truth registered there; --pred is sent to it)"
    )
    add_connection_arguments(group)
    group.add_argument(
        "--label",
        type=_label,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="with --service: a label the service stores with the evaluation (branch=main, commit=abc1234); "
        "repeatable (default: none)",
    )
    group.add_argument(
        "--project",
        metavar="NAME",
        help="with --service, in accounts mode: the project the evaluation belongs to (default: the ground "
        "truth's, else your only one)",
    )


def client_of(args: argparse.Namespace, *, progress: bool = False) -> Client:
    from ..client import Client, Retries

    quiet = getattr(args, "quiet", False)
    return Client(
        service_of(args),
        retries=Retries(within_s=args.retry_for),
        progress=progress and not quiet and sys.stderr.isatty(),
        on_retry=None if quiet else (lambda sentence: say(sentence)),
        allow_http=True if getattr(args, "allow_http", False) else None,
    )


def quota_left(client: Client, benchmark: str, phase: str | None, info: dict[str, Any]) -> str:
    """The quota left on the benchmark's phase as a sentence: the team's in a team ("the team lidar-lab has 1
    of 2 left today"), else the caller's. ``info``: the benchmark as :meth:`Client.benchmark` reads it."""
    from ..client import _shown

    team = None
    if int(info.get("team_size") or 1) > 1:
        mine = client.teams(benchmark).get("mine")
        team = _shown(mine.get("name")) if isinstance(mine, dict) else None
    quota = client.quota(benchmark, phase=phase)
    when = "today" if quota.days == 1 else f"in any {quota.days:g} days"
    who = f"the team {team} has" if team else "you have"
    return f"{who} {quota.left} of {quota.submissions} left {when}"


def exit_code(error: ServiceError) -> int:
    if isinstance(error, QuotaExceeded):
        return EXIT_QUOTA
    if isinstance(error, ServiceUnreachable):
        return EXIT_UNREACHABLE
    if error.refused_input:
        return EXIT_INPUT
    return EXIT_USAGE


def report(error: ServiceError) -> int:
    """Says a refusal on stderr (a refused submission: the validator's sentences, one a line) and returns the
    exit code it means."""
    if isinstance(error, SubmissionRefused) and error.problems:
        say(f"error: {error}")
        for line in error.problems:
            print(line, file=sys.stderr)
    else:
        say(f"error: {error}")
    return exit_code(error)


def _labels(args: argparse.Namespace) -> dict[str, str]:
    return dict(item.split("=", 1) for item in args.label)


def _unsupported(args: argparse.Namespace, names: dict[str, str]) -> None:
    given = [flag for attr, flag in names.items() if getattr(args, attr, None)]
    if given:
        raise ConfigError(f"{', '.join(given)} cannot be sent to a service (with --service): evaluate here instead")


def _evaluate(
    args: argparse.Namespace, gt: object, pred: object, *, curves: bool, errors: bool, keep: bool = True
) -> Any:
    """One evaluation done by the service: ``gt`` names its ground truth, ``pred`` is the file sent; ``keep``:
    stored as an evaluation (else evaluated for a gate and kept nowhere: no labels, no project)."""
    _unsupported(
        args,
        {
            "protocol_file": "--protocol-file",
            "gt_format": "--gt-format",
            "pred_format": "--pred-format",
            "split": "--split",
            "sharded": "--sharded",
            "cluster": "--cluster",
            "plot": "--plot",
            "plot_dir": "--plot-dir",
            "max_input_mb": "--max-input-mb",
            "max_frames": "--max-frames",
            "max_boxes_per_frame": "--max-boxes-per-frame",
            "max_boxes": "--max-boxes",
            "max_frame_pairs": "--max-frame-pairs",
            "max_pairs": "--max-pairs",
        },
    )
    if Path(str(gt)).exists():
        raise ConfigError(
            f"--gt {gt}: with --service, --gt names a ground truth registered on the service (GET "
            "/v1/ground-truths lists them), not a file here"
        )
    with client_of(args, progress=True) as client:
        return client.evaluate(
            str(pred),
            str(gt),
            protocol=args.protocol,
            classes=args.classes,
            iou=args.iou or (),
            ranges=args.ranges,
            coco=args.coco,
            lidar_only=args.lidar_only,
            curves=curves,
            errors=errors,
            labels=_labels(args) if keep else None,
            project=args.project if keep else None,
            keep=keep,
        )


def run_evaluation(args: argparse.Namespace) -> int:
    """``kitti-eval --service URL --gt NAME --pred FILE``: the document a local run prints, computed there."""
    from ..report.render import OutputFormat

    if len(args.gt) != 1 or len(args.pred) != 1:
        raise ConfigError("--service evaluates one --pred against one --gt (a name the service registered)")
    if args.errors and args.format is not OutputFormat.JSON:
        raise ConfigError("--errors with --service prints as --format json")
    evaluation = _evaluate(args, args.gt[0], args.pred[0], curves=args.curves, errors=args.errors)
    if not args.quiet:
        for w in evaluation.document.get("warnings", []):
            say(f"warning: {w}")
        say(f"stored as evaluation {evaluation.id} ({args.service}/v1/evaluations/{evaluation.id})")
    emit(evaluation.render(args.format.value), args.output)
    return EXIT_OK


def _read_only(args: argparse.Namespace) -> bool:
    """Whether the token may only read (``GET /v1/me``): then a gate's evaluation is made without keeping it."""
    with client_of(args) as client:
        return bool(client.whoami()["read_only"])


def run_gate(args: argparse.Namespace, *, errors: bool = False) -> tuple[dict, dict | None]:
    """``kitti-eval gate --service``: the documents a gate reads, evaluated by the service: the current one from
    --pred (stored as an evaluation with a token that may write; with a read-only token evaluated for this gate
    and kept nowhere, which is said), the baseline the newest evaluation labelled --baseline-label against the
    same ground truth (the project's history), or a stored evaluation's id (``errors``: with the error
    decomposition, for rules on error types)."""
    from ..errors import ServiceError

    if args.result or args.sharded or args.significant:
        raise ConfigError("--service gates --pred evaluated there: not --result, --sharded or --significant")
    if not (args.gt and args.pred):
        raise ConfigError("--service gates --pred against --gt, the name of a ground truth registered there")
    if args.baseline is not None and args.baseline_label:
        raise ConfigError("give --baseline (an evaluation id) or --baseline-label, not both")
    keep = not _read_only(args)
    if not keep and args.label and not args.quiet:
        say(f"warning: --label {' '.join(args.label)} is not stored: the evaluation is not kept")
    # the baseline first: a label with no evaluation is said before --pred is sent and evaluated
    baseline = None
    with client_of(args) as client:
        if args.baseline_label:
            key, _, value = args.baseline_label.partition("=")
            found = client.evaluations(gt=str(args.gt), labels={key: value}, limit=1)
            if not found:
                raise ServiceError(
                    f"{args.service}: no evaluation labelled {args.baseline_label} against {args.gt}",
                    status=404,
                    code="not_found",
                )
            baseline = client.evaluation(found[0]["id"])
        elif args.baseline is not None:
            baseline = client.evaluation(str(args.baseline))
    current = _evaluate(args, args.gt, args.pred, curves=False, errors=errors, keep=keep)
    if keep and not args.quiet:
        say(f"stored as evaluation {current.id} ({args.service}/v1/evaluations/{current.id})")
    elif not args.quiet:
        say(
            f"not stored: the token is read-only, so {args.service} evaluated --pred for this gate and kept "
            "nothing (no evaluation in the history, the predictions not kept)"
        )
    if baseline is not None and not args.quiet:
        say(f"baseline: evaluation {baseline.id}")
    return current.document, None if baseline is None else baseline.document
