"""``kitti-eval validate``: a benchmark submission checked offline, with the service's own sentences.

Exit 0 when the submission is valid (a summary on stdout), 1 when it is not (one problem a line on stderr) or
cannot be read, 2 on usage errors.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from .common import EXIT_INPUT, EXIT_OK

__all__ = ["add_parser", "run", "fetch_frames", "fetch_set"]

_TIMEOUT_S = 60


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "validate",
        help="check a benchmark submission before sending it (every test frame once, 16 fields a line, ...)",
        description="Check a benchmark submission the way the service checks it before it counts: every test "
        "frame present exactly once, 16 fields a line, known class names, finite numbers, a bounded number of "
        "boxes a frame. Exit 0 valid, 1 invalid (the problems on stderr, one a line), 2 usage error.",
    )
    p.add_argument("file", type=Path, help="a zip or tar of KITTI result txt files, a folder of them, or a result.pkl")
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--frames",
        type=Path,
        metavar="IDS_FILE",
        help="the test set's frame ids, one a line (ImageSets/test.txt)",
    )
    source.add_argument(
        "--benchmark",
        metavar="URL",
        help="a hosted benchmark, e.g. http://host:8000/benchmarks/NAME: its frame ids are fetched from the service",
    )
    p.add_argument(
        "--token",
        metavar="TOKEN",
        help="with --benchmark: a token for a benchmark that is not public (default: $KITTI_EVAL_TOKEN)",
    )
    p.add_argument(
        "--max-boxes",
        type=int,
        default=None,
        metavar="N",
        help="boxes a frame may hold (default: the service's default, 1000)",
    )
    p.set_defaults(run=run)
    return p


def run(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from ..io.loaders import read_split
    from ..io.submission import SubmissionRules, validate_submission

    if args.max_boxes is not None and args.max_boxes < 1:
        raise ConfigError("--max-boxes must be >= 1")
    extra = {} if args.max_boxes is None else {"max_boxes_per_frame": args.max_boxes}
    frames, labels = (
        (read_split(args.frames), "test") if args.frames is not None else fetch_set(args.benchmark, args.token)
    )
    rules = SubmissionRules(frames=tuple(frames), labels=labels, **extra)
    outcome = validate_submission(args.file, rules)
    if not outcome.ok:
        for line in outcome.lines():
            print(line, file=sys.stderr)
        return EXIT_INPUT
    print(f"{args.file}: valid: {outcome.frames} frames, {outcome.boxes} boxes")
    return EXIT_OK


def fetch_frames(url: str, token: str | None = None) -> list[str]:
    """The test frame ids of the benchmark at ``url`` (``http(s)://HOST/benchmarks/NAME``, or its API path
    ``/v1/benchmarks/NAME``), from the service's ``GET /v1/benchmarks/NAME/frames``."""
    return fetch_set(url, token)[0]


def fetch_set(url: str, token: str | None = None) -> tuple[list[str], str]:
    """:func:`fetch_frames`, and what the service calls them: ``test`` (a sealed test set) or ``validation`` (the
    labelled set of a phase on open labels)."""
    import urllib.error  # here: every other command would import the HTTP client (and ssl) for nothing
    import urllib.request

    from ..client_config import token_for  # the standard library only: the HTTP client it uses is loaded when it sends
    from ..core.frames import normalize_frame_id
    from ..errors import ConfigError, InputError

    found = re.match(r"^(https?://[^/?#]+)(?:/v1)?/benchmarks/([A-Za-z0-9][A-Za-z0-9._-]{0,63})/?$", url.strip())
    if found is None:
        raise ConfigError(f"--benchmark: expected http(s)://HOST/benchmarks/NAME, got {url!r}")
    base, name = found.groups()
    request = urllib.request.Request(f"{base}/v1/benchmarks/{name}/frames", headers={"Accept": "application/json"})
    token = token_for(base, token)  # --token, else $KITTI_EVAL_TOKEN, else the one kitti-eval login saved
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=_TIMEOUT_S) as response:  # noqa: S310 - http(s) checked above
            body = json.loads(response.read(64 << 20))
    except urllib.error.HTTPError as e:
        try:
            message = json.loads(e.read(1 << 16))["error"]["message"]
        except Exception:  # noqa: BLE001 - not the service's error shape
            message = e.reason
        raise InputError(f"{url}: the service answered {e.code}: {message}") from None
    except (urllib.error.URLError, OSError, ValueError) as e:
        raise InputError(f"{url}: cannot fetch the frame ids: {getattr(e, 'reason', e)}") from None
    frames = body.get("frames") if isinstance(body, dict) else None
    if not isinstance(frames, list) or not frames:
        raise InputError(f"{url}: the answer holds no frame ids")
    labels = "validation" if body.get("labels") == "validation" else "test"
    return [normalize_frame_id(f) for f in frames], labels
