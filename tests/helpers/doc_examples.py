"""The examples of the documentation (README.md and docs/**/*.md): where each is, and which the tests run.

A test that runs an example takes it with :func:`take` when its module is imported, so that
tests/docs/test_doc_examples.py can check that every ``bash`` and ``python`` block is run by some test, or says
why not in an HTML comment on the line just before it::

    <!-- not run: needs your KITTI data -->
"""

from __future__ import annotations

import inspect
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CHECKED = ("bash", "python", "toml", "yaml")  # the languages whose every block must be run or say why not

_FENCE = re.compile(r"^```(?P<lang>[\w-]*)[^\n]*\n(?P<code>.*?)^```[ \t]*$", re.S | re.M)
_NOT_RUN = re.compile(r"^<!-- not run: (?P<why>\S.*?) -->$")

#: (page, line of the opening fence) of every example a test took, with the module that took it
TAKEN: dict[tuple[str, int], str] = {}


@dataclass(frozen=True)
class Example:
    page: str  # relative to the repository: "README.md", "docs/service/accounts.md"
    line: int  # of the opening fence, from 1
    lang: str
    code: str
    not_run: str | None  # the reason its "<!-- not run: ... -->" comment gives

    def __str__(self) -> str:
        return f"{self.page}:{self.line} ({self.lang})"


def pages() -> list[str]:
    """README.md and every page of docs/, as paths relative to the repository."""
    return ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").rglob("*.md"))]


def text(page: str) -> str:
    return (ROOT / page).read_text(encoding="utf-8")


def examples(page: str) -> list[Example]:
    """Every fenced block of ``page``, in order."""
    source = text(page)
    found = []
    for m in _FENCE.finditer(source):
        line = source.count("\n", 0, m.start()) + 1
        before = [s.strip() for s in source[: m.start()].splitlines() if s.strip()]
        marker = _NOT_RUN.match(before[-1]) if before else None
        found.append(Example(page, line, m["lang"], m["code"], marker["why"] if marker else None))
    return found


def take(page: str, after: str, count: int = 1, lang: str = "bash") -> list[Example]:
    """The first ``count`` blocks in ``lang`` after the first line of ``page`` that holds ``after``, recorded as
    run by the calling test module."""
    source = text(page)
    start = source.index(after)  # ValueError: the page lost the text the test finds its examples by
    line = source.count("\n", 0, start) + 1
    chosen = [e for e in examples(page) if e.line > line and e.lang == lang][:count]
    assert len(chosen) == count, f"fewer than {count} {lang} blocks after {after!r} in {page}"
    frame = inspect.currentframe()
    caller = frame.f_back.f_globals.get("__name__", "?") if frame and frame.f_back else "?"
    for example in chosen:
        TAKEN[(example.page, example.line)] = caller
    return chosen


def run_bash(script: str, cwd: Path, *, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    """Run an example as a reader would (``set -euo pipefail``), with this checkout's ``kitti-eval`` and ``python``
    first on the PATH and none of the tester's ``KITTI_EVAL_*`` settings; its exit code asserted 0."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("KITTI_EVAL_")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    proc = subprocess.run(
        ["bash", "-c", "set -euo pipefail\n" + script],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc
