"""``kitti-eval submit``: a benchmark submission sent to the service and followed until it is scored.

``submit`` checks the file here first, as ``kitti-eval validate --benchmark`` does (a refused file costs no
quota and is not sent), sends it with an idempotency key of its own (sent again while the service is away, it
counts once), waits for its job and prints the scores the service shows the participant.

Exit 0 scored, 1 the file is refused (the validator's sentences on stderr, here or from the service), 2 usage
or a request the service refuses (no token, unknown benchmark, closed), 4 over the quota (when the next
submission is accepted on stderr), 5 the service could not be reached within ``--retry-for``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..errors import ConfigError
from .common import EXIT_OK, emit, say
from .remote import add_connection_arguments, client_of, quota_left

if TYPE_CHECKING:
    from ..client import Client, Submission

__all__ = ["add_parser", "run", "render_submission", "standing"]

_EPILOG = (
    "Exit codes: 0 scored, 1 the file is refused (nothing counted), 2 usage error or a request the service "
    "refuses, 4 over the quota (the message says when the next submission is accepted), 5 the service could not "
    "be reached within --retry-for."
)


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "submit",
        help="send a submission to a hosted benchmark and print its scores (exit 4 over the quota)",
        description="Send a submission to a benchmark of a service: checked here first as 'kitti-eval validate' "
        "checks it (a refused file costs no quota and is not sent), sent with a progress bar and an idempotency "
        "key (sent again while the service is away, restarting or busy, it counts once), then followed until it "
        "is scored; prints the scores the service shows you.",
        epilog=_EPILOG,
    )
    p.add_argument(
        "file",
        type=Path,
        help="a zip or tar of KITTI result txt files (one a test frame), a folder of them (sent as a tar.gz), or a "
        "result.pkl",
    )
    p.add_argument(
        "--benchmark", required=True, metavar="NAME", help="the benchmark's name (its page: /benchmarks/NAME)"
    )
    p.add_argument(
        "--phase",
        metavar="PHASE",
        help="the benchmark's phase to submit to, checked against that phase's test frames (default: its current "
        "phase)",
    )
    add_connection_arguments(p, saved=True)
    p.add_argument(
        "--format",
        choices=["table", "json", "markdown"],
        default="table",
        help="the scores as text, as the service's JSON view of the submission, or as Markdown (default: table)",
    )
    p.add_argument(
        "--no-wait",
        dest="wait",
        action="store_false",
        help="print the submission's id once it is accepted, without waiting for its scores (default: wait)",
    )
    p.add_argument(
        "--wait-for",
        type=float,
        default=3600.0,
        metavar="S",
        help="longest wait for the scores once accepted (default: 3600)",
    )
    p.add_argument(
        "--idempotency-key",
        metavar="KEY",
        help="the key sent with the submission (1-255 visible ASCII characters): the same key again answers with "
        "the submission it made, counted once; e.g. a CI run's id, so that the job run again does not submit twice "
        "(default: the key saved for this file and phase by a run that did not show it scored, else a new one)",
    )
    p.add_argument(
        "--new",
        action="store_true",
        help="submit the file as a new submission, counted again, even if a run killed before it showed the "
        "scores sent the same file to the same phase (default: such a run's submission is answered, counted once)",
    )
    p.add_argument("--output", "-o", type=Path, help="write the scores here instead of stdout (default: stdout)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar, no retry messages (default: off)")
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    if not args.file.exists():
        raise ConfigError(f"{args.file}: no such file or folder")
    if not args.wait_for > 0:
        raise ConfigError("--wait-for must be > 0")
    if args.new and args.idempotency_key:
        raise ConfigError("give --new or --idempotency-key, not both")
    with client_of(args, progress=True) as client:
        try:
            submission = client.submit(
                args.file,
                args.benchmark,
                wait=args.wait,
                wait_s=args.wait_for,
                idempotency_key=args.idempotency_key,
                phase=args.phase,
                new=args.new,
            )
        except KeyboardInterrupt:
            again = f"with --idempotency-key {args.idempotency_key} " if args.idempotency_key else ""
            say(
                f"interrupted: the submission may have been accepted; the same command {again}again answers with "
                "it instead of submitting again (--new submits it again, counted again)"
            )
            raise
        if not args.quiet:
            for line in standing(client, submission, args.benchmark, args.phase):
                say(line)
        if not args.wait:
            emit(submission.id + "\n", args.output)
            return EXIT_OK
        key = client.benchmark(args.benchmark).get("key") or []
    emit(render_submission(submission, args.format, key=key), args.output)
    return EXIT_OK


def standing(client: Client, submission: Submission, benchmark: str, phase: str | None) -> list[str]:
    """Where a submission stands, as ``submit`` says it on stderr: the phase it went to, the quota left (the
    team's, in a team), its page and how to publish it; first, when it is the answer to an earlier run's key,
    that it was counted once."""
    from ..client import _shown

    lines = []
    if submission.reused:
        lines.append(
            "this file was sent to this phase by a run that did not show its scores: that run's submission, "
            "counted once (--new submits it again, counted again)"
        )
    info = client.benchmark(benchmark)
    shown_phase = submission.view.get("phase") or phase or info.get("phase")
    state = submission.status if submission.status in ("scored", "failed") else f"accepted ({submission.status})"
    left = quota_left(client, benchmark, phase, info)
    lines.append(f"submission {submission.id} to {benchmark}, phase {_shown(shown_phase)}: {state}; {left}")
    lines.append(f"its page: {client.service}/benchmarks/{benchmark}/submissions/{submission.id}")
    if submission.status == "scored" and not submission.view.get("published"):
        lines.append(
            f"to show it on the board: kitti-eval publish {submission.id} --benchmark {benchmark} "
            '--method "YOUR METHOD"'
        )
    return lines


def _key_value(submission: Submission, key: list[str]) -> float | None:
    values = [(submission.scores or {}).get(column) for column in key]
    if not key or any(v is None for v in values):
        return None
    return round(sum(v for v in values if v is not None) / len(values), 4)


def render_submission(submission: Submission, fmt: str, *, key: list[str] | None = None) -> str:
    """A scored submission as ``submit`` prints it: the scores the service shows its participant."""
    if fmt == "json":
        return json.dumps(submission.view, indent=2) + "\n"
    scores = submission.scores or {}
    part = submission.scored_on
    where = "the public part of the test set" if part == "public" else "the whole test set"
    key_value = _key_value(submission, key or [])
    key_name = " + ".join(key or [])
    if fmt == "markdown":
        lines = [
            f"### Submission `{submission.id}` to `{submission.benchmark}`: {submission.status}",
            "",
            f"Scores on {where}.",
            "",
            "| column | AP |",
            "|---|---:|",
        ]
        if key_value is not None:
            lines.append(f"| **key** ({key_name}) | **{key_value:.2f}** |")
        lines += [f"| {c} | {'' if v is None else f'{v:.2f}'} |" for c, v in scores.items()]
        return "\n".join(lines) + "\n"
    width = max([len(c) for c in scores] + [3])
    lines = [f"submission {submission.id} to {submission.benchmark}: {submission.status}, on {where}"]
    if key_value is not None:
        lines.append(f"{'key':<{width}}  {key_value:8.4f}  ({key_name})")
    lines += [f"{c:<{width}}  {'-' if v is None else f'{v:.4f}':>8}" for c, v in scores.items()]
    return "\n".join(lines) + "\n"
