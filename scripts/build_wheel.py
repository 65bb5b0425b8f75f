"""Build kitti-eval's platform wheels: the package with its numba kernels compiled in, for a generic CPU.

A wheel built by plain ``pip wheel .`` (or an sdist, or an editable install) holds the sources only, and the
first run after installing it compiles every kernel (about 10 s of wall time, 15 s of CPU on two cores).
This script builds, for each Python interpreter given, a wheel that also carries the kernels:

1. the package's sources are copied into a temporary folder (the checkout is never written);
2. ``python -m kitti_eval._jit --all``'s warm-up runs there, under that interpreter and the numba the wheel
   will require, with ``NUMBA_CPU_NAME=generic`` in that process only: every kernel of every entry point is
   compiled for the generic CPU of the platform (x86-64 without AVX and the like; it runs on any x86-64) into
   the copy's ``__pycache__`` folders;
3. those cache files move to ``kitti_eval/_kernels/`` (folders named as the package's) beside a manifest
   naming the numba and Python versions and the target (``kitti_eval.core.kernel_cache`` reads them);
4. the wheel is built from the copy with ``numba==<that version>`` as its requirement (numba refuses cache
   files written by another version) and tagged for the interpreter and platform, e.g.
   ``kitti_eval-0.1.0-cp311-cp311-linux_x86_64.whl``.

Usage::

    python scripts/build_wheel.py                          # this interpreter, into dist/
    python scripts/build_wheel.py --python python3.12 --python python3.13 --out wheelhouse

An interpreter other than this one (or another ``--numba``) gets its own temporary virtual environment with
the package's dependencies installed from the package index.
"""

from __future__ import annotations

import argparse
import base64
import csv
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: what the wheel is built from (as the Dockerfile copies it)
SOURCES = ("pyproject.toml", "README.md", "kitti_eval", "server")
SHIPPED = Path("kitti_eval") / "_kernels"

# run in the build's copy: compile every kernel, count the compilations, describe the interpreter and target
_COMPILE = r"""
import json, sys, sysconfig
from kitti_eval._jit import compilations

with compilations() as compiled:
    import kitti_eval
    from kitti_eval import _jit

    _jit.warm_up(everything=True)

import numba
from numba.core.registry import cpu_target
from kitti_eval.core import kernel_cache

version = f"{sys.version_info[0]}{sys.version_info[1]}"
print(json.dumps({
    "package": kitti_eval.__file__,
    "compiled": compiled,
    "numba": numba.__version__,
    "python": kernel_cache.python_tag(),
    "target": list(cpu_target.target_context.codegen().magic_tuple()),
    "implementation": sys.implementation.name,
    "tags": [f"cp{version}", f"cp{version}{getattr(sys, 'abiflags', '')}",
             sysconfig.get_platform().replace("-", "_").replace(".", "_")],
}))
"""


def _run(argv: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(argv, capture_output=True, text=True, check=False, **kwargs)  # type: ignore[call-overload]
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, argv[:6]))} failed ({done.returncode}):\n{done.stderr[-4000:]}")
    return done


def _dependencies(numba_version: str) -> list[str]:
    """The package's requirements, numba pinned to ``numba_version``."""
    with open(ROOT / "pyproject.toml", "rb") as fh:
        deps = tomllib.load(fh)["project"]["dependencies"]
    return [f"numba=={numba_version}" if re.match(r"numba\b", d) else d for d in deps]


def _interpreter(python: str, numba_version: str, work: Path) -> str:
    """An interpreter with ``numba_version`` and the package's other requirements: ``python`` itself when it is
    this one and has that numba, else a new virtual environment of ``python``'s."""
    if Path(python).absolute() == Path(sys.executable).absolute():
        try:
            import numba

            if numba.__version__ == numba_version:
                return python
        except ImportError:
            pass
    env = Path(tempfile.mkdtemp(prefix="env-", dir=work))
    _run([python, "-m", "venv", str(env)])
    built = str(env / ("Scripts/python.exe" if os.name == "nt" else "bin/python"))
    pip = [built, "-m", "pip", "--disable-pip-version-check", "--quiet", "install"]
    _run([*pip, *_dependencies(numba_version)])
    return built


def _copy_sources(src: Path) -> None:
    src.mkdir(parents=True)
    skip = shutil.ignore_patterns("__pycache__", "*.py[cod]", "*.nbi", "*.nbc", "_kernels", "*.egg-info")
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=skip)
        else:
            shutil.copy2(ROOT / name, src / name)


def _compile(python: str, src: Path) -> dict:
    """Compile every kernel for the generic CPU into ``src``'s ``__pycache__`` folders."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_") and k != "PYTHONPATH"}
    env.update(NUMBA_CPU_NAME="generic", PYTHONPATH=str(src), PYTHONDONTWRITEBYTECODE="1")
    done = _run([python, "-c", _COMPILE], cwd=src, env=env, timeout=1800)
    info = dict(json.loads(done.stdout.strip().splitlines()[-1]))
    if Path(info["package"]).resolve().parent != (src / "kitti_eval").resolve():
        raise SystemExit(f"the warm-up imported {info['package']}, not the build's copy")
    if info["implementation"] != "cpython":
        raise SystemExit("numba's kernels are built for CPython only")
    if info["target"][1:] != ["generic", ""]:
        raise SystemExit(f"compiled for {info['target']}, not the generic CPU")
    return info


def _ship(src: Path, info: dict) -> int:
    """Move numba's cache files from the copy's ``__pycache__`` folders to ``kitti_eval/_kernels/``; write the
    manifest. Returns how many kernels (index files) it holds."""
    package, shipped = src / "kitti_eval", src / SHIPPED
    kernels = 0
    for cache in sorted(package.rglob("__pycache__")):
        for path in sorted(cache.iterdir()):
            if path.suffix in (".nbi", ".nbc"):
                target = shipped / cache.parent.relative_to(package) / path.name
                target.parent.mkdir(parents=True, exist_ok=True)
                path.replace(target)
                kernels += path.suffix == ".nbi"
        shutil.rmtree(cache)
    if kernels == 0:
        raise SystemExit("the warm-up left no kernels in numba's cache")
    manifest = {"numba": info["numba"], "python": info["python"], "target": info["target"], "kernels": kernels}
    (shipped / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    return kernels


def _pin_numba(pyproject: Path, numba_version: str) -> None:
    text = pyproject.read_text(encoding="utf-8")
    text, count = re.subn(r'"numba(?:\s*[<>=!~][^"]*)?"', f'"numba=={numba_version}"', text)
    if count != 1:
        raise SystemExit(f"expected one numba requirement in pyproject.toml, found {count}")
    pyproject.write_text(text, encoding="utf-8")


def _record_line(name: str, data: bytes) -> list[str]:
    digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
    return [name, f"sha256={digest}", str(len(data))]


def retag(wheel: Path, tag: str, out: Path) -> Path:
    """``wheel`` (pure, ``py3-none-any``) rewritten as a wheel for ``tag`` (``cp311-cp311-linux_x86_64``) in
    folder ``out``: its name, the WHEEL file's tag and purelib flag, the RECORD's hashes."""
    name, version = wheel.name.split("-")[:2]
    dist_info = f"{name}-{version}.dist-info"
    target = out / f"{name}-{version}-{tag}.whl"
    rows: list[list[str]] = []
    with zipfile.ZipFile(wheel) as old, zipfile.ZipFile(target, "w", zipfile.ZIP_DEFLATED) as new:
        for item in old.infolist():
            if item.filename == f"{dist_info}/RECORD":
                continue
            data = old.read(item)
            if item.filename == f"{dist_info}/WHEEL":
                lines = [
                    line
                    for line in data.decode().splitlines()
                    if not line.startswith(("Tag:", "Root-Is-Purelib:")) and line.strip()
                ]
                data = "\n".join([*lines, "Root-Is-Purelib: false", f"Tag: {tag}", ""]).encode()
            new.writestr(item, data, compress_type=zipfile.ZIP_DEFLATED)
            rows.append(_record_line(item.filename, data))
        rows.append([f"{dist_info}/RECORD", "", ""])
        record = io.StringIO()
        csv.writer(record, lineterminator="\n").writerows(rows)
        new.writestr(f"{dist_info}/RECORD", record.getvalue(), compress_type=zipfile.ZIP_DEFLATED)
    return target


def build(python: str, numba_version: str, out: Path) -> Path:
    """The platform wheel of ``python`` with its kernels, written into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="kitti-eval-wheel-") as tmp:
        work = Path(tmp)
        interpreter = _interpreter(python, numba_version, work)
        src = work / "src"
        _copy_sources(src)
        info = _compile(interpreter, src)
        if info["numba"] != numba_version:
            raise SystemExit(f"compiled with numba {info['numba']}, not {numba_version}")
        kernels = _ship(src, info)
        _pin_numba(src / "pyproject.toml", numba_version)
        dist = work / "dist"
        pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--quiet"]
        _run([*pip, "wheel", "--no-deps", str(src), "-w", str(dist)])
        (pure,) = dist.glob("*.whl")
        wheel = retag(pure, "-".join(info["tags"]), out)
        print(
            f"{wheel}  {wheel.stat().st_size / 2**20:.2f} MiB  {kernels} kernels for {info['target'][0]} "
            f"(generic CPU)  numba=={numba_version}"
        )
        return wheel


def _default_numba() -> str:
    try:
        import numba
    except ImportError:
        raise SystemExit("numba is not installed here: say which version the wheels need with --numba") from None
    return str(numba.__version__)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--python",
        action="append",
        help="an interpreter to build a wheel for (repeatable; default: this one)",
    )
    parser.add_argument("--numba", help="the numba version the wheels need (default: the one installed here)")
    parser.add_argument("--out", type=Path, default=ROOT / "dist", help="where to write the wheels (default: dist/)")
    args = parser.parse_args(argv)
    numba_version = args.numba or _default_numba()
    for python in args.python or [sys.executable]:
        build(shutil.which(python) or python, numba_version, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
