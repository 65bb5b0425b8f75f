"""``kitti-eval validate``: a benchmark submission checked offline, with the service's own sentences.

Exit 0 when the submission is valid (a summary on stdout), 1 when it is not (one problem a line on stderr) or
cannot be read, 2 on usage errors.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from .common import EXIT_INPUT, EXIT_OK

__all__ = ["add_parser", "run"]


def add_parser(sub: Any) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "validate",
        help="check a benchmark submission before sending it (every test frame once, 16 fields a line, ...)",
        description="Check a benchmark submission the way the service checks it before it counts: every test "
        "frame present exactly once, 16 fields a line, known class names, finite numbers, a bounded number of "
        "boxes a frame. Exit 0 valid, 1 invalid (the problems on stderr, one a line), 2 usage error.",
    )
    p.add_argument("file", type=Path, help="a zip or tar of KITTI result txt files, a folder of them, or a result.pkl")
    p.add_argument(
        "--frames",
        required=True,
        type=Path,
        metavar="IDS_FILE",
        help="the test set's frame ids, one a line (ImageSets/test.txt)",
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
    rules = SubmissionRules(frames=tuple(read_split(args.frames)), **extra)
    outcome = validate_submission(args.file, rules)
    if not outcome.ok:
        for line in outcome.lines():
            print(line, file=sys.stderr)
        return EXIT_INPUT
    print(f"{args.file}: valid: {outcome.frames} frames, {outcome.boxes} boxes")
    return EXIT_OK
