"""The platform wheel carries its kernels: installed into a fresh environment, its first run compiles nothing
and gives the numbers the kernels compiled here give.

``scripts/build_wheel.py`` compiles every kernel for the generic CPU of the platform into the wheel
(``kitti_eval/_kernels/``); :mod:`kitti_eval.core.kernel_cache` loads them where numba's cache has none.
The wheel is built once for the module (about 20 s: a compile of every kernel and a wheel build) and
installed into a new virtual environment for each test, which finds numba and numpy in this environment.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path
from typing import Any

import numba
import pytest
from test_packaging import install_in_fresh_venv

import kitti_eval

ROOT = Path(__file__).resolve().parents[2]

# kitti-eval demo and every kernel of every entry point (the service's warm-up), counting numba's compilations
_COUNT = """
import json, sys
from kitti_eval._jit import compilations

with compilations() as compiled:
    import kitti_eval
    from kitti_eval import _jit
    from kitti_eval.cli import main

    code = main(["demo", "--format", "json", "--quiet", "--output", sys.argv[1]])
    _jit.warm_up(everything=True)
    cached = _jit.kernels_cached() and _jit.loader_cached()
print(json.dumps({"package": kitti_eval.__file__, "code": code, "compiled": compiled, "cached": cached}))
"""

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled"),
]


def _tag() -> str:
    version = f"{sys.version_info[0]}{sys.version_info[1]}"
    platform = sysconfig.get_platform().replace("-", "_").replace(".", "_")
    return f"cp{version}-cp{version}{getattr(sys, 'abiflags', '')}-{platform}"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("wheelhouse")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    done = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "build_wheel.py"), "--out", str(out)],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    (built,) = out.glob("*.whl")
    return built


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_") and k != "PYTHONPATH"}
    return dict(env, **extra)


def _first_use(python: Path, tmp_path: Path, **env: str) -> tuple[dict[str, Any], dict[str, Any]]:
    out = tmp_path / "demo.json"
    done = subprocess.run(
        [str(python), "-c", _COUNT, str(out)],
        cwd=tmp_path,
        env=_env(**env),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    result = dict(json.loads(done.stdout.strip().splitlines()[-1]))
    assert result["code"] == 0 and Path(result["package"]).resolve().is_relative_to(python.parent.parent.resolve())
    return result, json.loads(out.read_text())


def _host_document(tmp_path: Path) -> dict[str, Any]:
    """The demo's document from this environment's kernels, compiled for this machine's CPU."""
    from numba.core.registry import cpu_target

    from kitti_eval.cli import main

    if cpu_target.target_context.codegen().magic_tuple()[1] == "generic":
        pytest.skip("this process compiles for the generic CPU itself (NUMBA_CPU_NAME=generic)")
    out = tmp_path / "host.json"
    assert main(["demo", "--format", "json", "--quiet", "--output", str(out)]) == 0
    return dict(json.loads(out.read_text()))


def test_the_wheel_is_tagged_for_this_python_and_platform_and_pins_numba(wheel: Path) -> None:
    assert wheel.name == f"kitti_eval-{kitti_eval.__version__}-{_tag()}.whl"
    names = set(zipfile.ZipFile(wheel).namelist())
    meta = zipfile.Path(wheel, f"kitti_eval-{kitti_eval.__version__}.dist-info/")
    assert f"Tag: {_tag()}" in (meta / "WHEEL").read_text().splitlines()
    assert "Root-Is-Purelib: false" in (meta / "WHEEL").read_text().splitlines()
    requires = [line for line in (meta / "METADATA").read_text().splitlines() if line.startswith("Requires-Dist:")]
    assert f"Requires-Dist: numba=={numba.__version__}" in requires
    assert not any(line.startswith("Requires-Dist: numba") and "==" not in line for line in requires)
    manifest = json.loads(zipfile.Path(wheel, "kitti_eval/_kernels/manifest.json").read_text())
    assert manifest["numba"] == numba.__version__ and manifest["target"][1:] == ["generic", ""]
    index = {n for n in names if n.startswith("kitti_eval/_kernels/") and n.endswith(".nbi")}
    assert len(index) == manifest["kernels"] > 20
    assert "kitti_eval/_kernels/core/" + "matching._pass2" in {n.rsplit("-", 1)[0] for n in index}
    assert not any("__pycache__" in n for n in names)  # the build's own caches stay out


def test_a_fresh_install_of_the_wheel_compiles_nothing_and_gives_the_same_document(wheel: Path, tmp_path: Path) -> None:
    python = install_in_fresh_venv(wheel, tmp_path / "venv", dependencies_from_here=True)
    installed = python.parent.parent
    # the first use: kitti-eval demo, then the service's warm-up of every kernel; numba's cache in an empty
    # folder of the test's
    cache = tmp_path / "numba-cache"
    result, document = _first_use(python, tmp_path, NUMBA_CACHE_DIR=str(cache))
    assert result["compiled"] == []
    assert result["cached"]  # the CLI sees the kernels: no "compiling" notice, no background compile
    assert not list(cache.rglob("*.nbi"))  # and saves nothing
    assert document == _host_document(tmp_path)  # generic kernels, the same numbers to the last digit
    # the same without NUMBA_CACHE_DIR: numba's place is then the package's __pycache__, which stays empty
    again, _ = _first_use(python, tmp_path)
    assert again["compiled"] == []
    assert not list(installed.rglob("__pycache__/*.nb[ic]"))


def test_the_console_script_says_nothing_of_compiling(wheel: Path, tmp_path: Path) -> None:
    python = install_in_fresh_venv(wheel, tmp_path / "venv", dependencies_from_here=True)
    script = python.parent / ("kitti-eval.exe" if sys.platform == "win32" else "kitti-eval")
    cache = tmp_path / "numba-cache"
    done = subprocess.run(
        [str(script), "demo"], env=_env(NUMBA_CACHE_DIR=str(cache)), capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr
    assert "compiling" not in done.stderr and "Car" in done.stdout
    assert not list(cache.rglob("*.nbi"))


def test_a_read_only_installation_still_loads_them(wheel: Path, tmp_path: Path) -> None:
    """numba cannot write next to a read-only package and caches in the user's folder instead: the shipped
    kernels are read from the package all the same (the package is mounted read-only in a mount namespace
    of its own, which needs ``unshare``)."""
    unshare = shutil.which("unshare")
    if unshare is None or subprocess.run([unshare, "-m", "true"], capture_output=True).returncode != 0:
        pytest.skip("no unshare -m here")
    python = install_in_fresh_venv(wheel, tmp_path / "venv", dependencies_from_here=True)
    get = [str(python), "-c", "import kitti_eval; print(kitti_eval.__file__)"]
    package = Path(subprocess.run(get, capture_output=True, text=True, check=True).stdout.strip()).parent
    out, home = tmp_path / "demo.json", tmp_path / "home"
    script = (
        f"mount --bind {package} {package} && mount -o remount,bind,ro {package} && "
        f"! touch {package}/probe 2>/dev/null && exec {python} -c '{_COUNT}' {out}"
    )
    done = subprocess.run(
        [unshare, "-m", "sh", "-c", script],
        cwd=tmp_path,
        env=_env(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache")),
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    if done.returncode != 0 and "mount" in done.stderr:
        pytest.skip(f"cannot mount read-only here: {done.stderr.strip()[-200:]}")
    assert done.returncode == 0, done.stdout + done.stderr
    assert json.loads(done.stdout.strip().splitlines()[-1])["compiled"] == []
    assert not list(home.rglob("*.nbi"))


def test_the_service_from_the_wheel_warms_up_and_evaluates_without_compiling(wheel: Path, tmp_path: Path) -> None:
    """``kitti-eval serve`` of the installed wheel: ready once its warm-up has loaded every kernel, an upload
    of the demo gives the demo's numbers, and numba's cache (in a folder of the test's) stays empty: a kernel
    compiled in the service's process would have been saved there."""
    from server_helpers import LiveServer

    from kitti_eval.demo import demo_paths

    python = install_in_fresh_venv(wheel, tmp_path / "venv", dependencies_from_here=True)
    cache = tmp_path / "numba-cache"
    where = [str(python), "-c", "import kitti_eval_server; print(kitti_eval_server.__file__)"]
    served = subprocess.run(where, cwd=tmp_path, capture_output=True, text=True, check=True).stdout.strip()
    assert Path(served).is_relative_to(tmp_path / "venv")  # the service the server below runs is the wheel's
    environ = {"NUMBA_CACHE_DIR": str(cache)}
    server = LiveServer(tmp_path / "data", via_serve=True, python=python, environ=environ).start()
    try:
        with server.client() as client, open(demo_paths()[1], "rb") as predictions:
            done = client.post("/v1/evaluations", data={"gt": "demo"}, files={"predictions": predictions})
        log = server.log_path.read_text()  # all of it: the readiness polls while the workers start come after
    finally:
        server.stop()
    assert done.status_code == 201, done.text
    assert done.json()["ap"] == _host_document(tmp_path)["ap"]
    assert "kernels warm in" in log, log
    assert not list(cache.rglob("*.nbi"))
