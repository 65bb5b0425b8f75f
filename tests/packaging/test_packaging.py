"""What the package installs: ``kitti_eval`` and the service as ``kitti_eval_server`` (from the repository's
``server/`` folder), and no top-level ``server`` that would take the name from every other project."""

from __future__ import annotations

import ast
import importlib.util
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

from kitti_eval.demo import DEMO_FILES

ROOT = Path(__file__).resolve().parents[2]
#: import name -> the folder it is installed from
SOURCES = {"kitti_eval": ROOT / "kitti_eval", "kitti_eval_server": ROOT / "server"}


def _setuptools() -> dict:
    with open(ROOT / "pyproject.toml", "rb") as fh:
        return tomllib.load(fh)["tool"]["setuptools"]


def _source_files(pattern: str) -> set[str]:
    """The package files matching ``pattern`` as the wheel names them (``server/x.py`` is
    ``kitti_eval_server/x.py``), without numba's and Python's caches."""
    found = set()
    for name, folder in SOURCES.items():
        for path in folder.rglob(pattern):
            if "__pycache__" not in path.parts:
                found.add("/".join([name, *path.relative_to(folder).parts]))
    return found


def test_every_package_is_listed_under_its_installed_name() -> None:
    config = _setuptools()
    packages = {p.rpartition("/")[0].replace("/", ".") for p in _source_files("__init__.py")}
    assert set(config["packages"]) == packages
    assert "kitti_eval_server.web" in packages and "kitti_eval.core" in packages
    assert config["package-dir"] == {"kitti_eval_server": "server"}
    assert config["package-data"]["kitti_eval_server"] == [
        "web/templates/*",
        "web/static/*",
        "store/migrations/script.py.mako",  # the template of a new revision (docs/development)
    ]


def test_the_installed_service_is_kitti_eval_server_and_reads_the_checkout() -> None:
    import kitti_eval_server
    from kitti_eval_server.web import STATIC_DIR

    assert Path(kitti_eval_server.__file__) == ROOT / "server" / "__init__.py"
    assert STATIC_DIR == ROOT / "server" / "web" / "static"
    assert {p.name for p in STATIC_DIR.iterdir()} >= {"app.css", "app.js"}


def test_outside_the_checkout_server_is_not_importable(tmp_path: Path) -> None:
    """The editable install maps ``kitti_eval_server`` to ``server/``; it does not put the repository on
    the path, so ``server`` resolves only where the working directory is the checkout."""
    code = "import importlib.util as u; print(*(u.find_spec(n) and u.find_spec(n).origin for n in {names}))"
    names = ["server", "kitti_eval_server", "kitti_eval"]
    out = subprocess.run(
        [sys.executable, "-c", code.format(names=names)], cwd=tmp_path, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["None", str(ROOT / "server/__init__.py"), str(ROOT / "kitti_eval/__init__.py")]


def test_nothing_imports_the_folder_name() -> None:
    """One module, one name: an ``import server`` anywhere (tests included) would load the service a
    second time, as other module objects, beside ``kitti_eval_server``."""
    offenders = []
    for folder in (ROOT / "kitti_eval", ROOT / "server", ROOT / "tests"):
        for path in sorted(folder.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                offenders += [f"{path.relative_to(ROOT)}:{node.lineno}" for n in names if n.split(".")[0] == "server"]
    assert offenders == []
    assert "server" not in sys.modules


PIP = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--quiet"]


def install_in_fresh_venv(wheel: Path, venv: Path, *, dependencies_from_here: bool = False) -> Path:
    """A new virtual environment (no pip of its own) with ``wheel`` alone installed in it, offline; its
    interpreter. With ``dependencies_from_here``, it finds the packages the wheel needs (numba, numpy, ...) in
    this environment's site-packages, after its own (a path in a .pth file: no .pth file of this environment
    runs there, so this environment's editable kitti-eval is not importable)."""
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / ("Scripts/python.exe" if sys.platform == "win32" else "bin/python")
    subprocess.run([*PIP, "--python", str(python), "install", "--no-deps", "--no-index", str(wheel)], check=True)
    if dependencies_from_here:
        import sysconfig

        get = [str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"]
        site = Path(subprocess.run(get, capture_output=True, text=True, check=True).stdout.strip())
        here = dict.fromkeys([sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]])
        (site / "_dependencies_from_here.pth").write_text("".join(f"{path}\n" for path in here))
    return python


@pytest.mark.slow
def test_the_wheel_installs_kitti_eval_server_and_no_server(tmp_path: Path) -> None:
    """Build the wheel from a copy of what the Dockerfile copies (no build folders land in the checkout),
    check its files, and install it alone into a fresh virtual environment."""
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("kitti_eval", "server"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    dist = tmp_path / "dist"
    subprocess.run([*PIP, "wheel", "--no-deps", str(src), "-w", str(dist)], check=True, capture_output=True)
    (wheel,) = dist.glob("*.whl")
    assert wheel.name == "kitti_eval-0.1.0-py3-none-any.whl"

    names = set(zipfile.ZipFile(wheel).namelist())
    assert {n.split("/")[0] for n in names} == {"kitti_eval", "kitti_eval_server", "kitti_eval-0.1.0.dist-info"}
    assert {n for n in names if n.endswith(".py")} == _source_files("*.py")
    templates = {p.name for p in (ROOT / "server" / "web" / "templates").glob("*.html")}
    assert {"base.html", "evaluation.html", "signin.html"} <= templates
    assert {n for n in names if n.startswith("kitti_eval_server/web/templates/")} == {
        f"kitti_eval_server/web/templates/{t}" for t in templates
    }
    assert {"kitti_eval_server/web/static/app.css", "kitti_eval_server/web/static/app.js"} < names
    shipped = {"kitti_infos_val.pkl.gz", "result.pkl.gz", "result_weaker.pkl.gz"}  # the names the docs give
    assert set(DEMO_FILES) == shipped and {f"kitti_eval/data/demo/{name}" for name in shipped} < names
    meta = zipfile.Path(wheel, "kitti_eval-0.1.0.dist-info/")
    assert (meta / "top_level.txt").read_text().split() == ["kitti_eval", "kitti_eval_server"]
    assert "kitti-eval = kitti_eval.cli:entry" in (meta / "entry_points.txt").read_text()

    venv = tmp_path / "venv"
    python = install_in_fresh_venv(wheel, venv)
    code = (
        "import importlib.util as u\n"
        "try:\n    import server\nexcept ModuleNotFoundError as e:\n    print(e.name)\n"
        "print(u.find_spec('kitti_eval_server').origin)\n"  # finding a top-level name imports nothing
    )
    out = subprocess.run([str(python), "-c", code], cwd=tmp_path, capture_output=True, text=True, check=True)
    missing, package = out.stdout.split()
    assert missing == "server"
    site = Path(package).parent.parent
    assert Path(package) == site / "kitti_eval_server" / "__init__.py" and site.is_relative_to(venv)
    assert (site / "kitti_eval_server" / "web" / "routes.py").is_file()
    assert {p.name for p in (site / "kitti_eval_server" / "web" / "templates").iterdir()} == templates
    assert not (site / "server").exists()
    assert importlib.util.find_spec("kitti_eval_server") is not None  # this environment's too
