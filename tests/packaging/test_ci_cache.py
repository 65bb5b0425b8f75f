"""The CI job of docs/cli/gates.md keeps numba's cache between runs: its steps, run on two installs of the package
made at different times, compile the kernels in the first and nothing in the second with the first's cache
restored."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numba
import pytest

import kitti_eval

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = Path(kitti_eval.__file__).resolve().parent

# kitti-eval demo, after every kernel of every entry point, counting numba's compilations (as tests/core/test_jit.py)
_COUNT = """
import json, sys
from kitti_eval._jit import compilations

with compilations() as compiled:
    import kitti_eval
    from kitti_eval import _jit
    from kitti_eval.cli import main

    _jit.warm_up()
    code = main(["demo", "--format", "json", "--quiet", "--output", sys.argv[1]])
print(json.dumps({"package": kitti_eval.__file__, "code": code, "compiled": compiled}))
"""


def _job() -> dict[str, Any]:
    yaml = pytest.importorskip("yaml")
    text = (ROOT / "docs" / "cli" / "gates.md").read_text()
    block = re.search(r"```yaml\n(name: kitti-gate\n.*?)```", text, re.S)
    assert block, "docs/cli/gates.md lost its CI job"
    return dict(yaml.safe_load(block.group(1))["jobs"]["gate"])


def _step(job: dict[str, Any], name: str) -> tuple[int, dict[str, Any]]:
    for i, step in enumerate(job["steps"]):
        if name in (step.get("name"), step.get("id"), step.get("uses")):
            return i, step
    raise AssertionError(f"no step {name!r} in the CI job of docs/cli/gates.md")


def test_the_readme_job_keeps_numbas_cache_under_kitti_evals_key() -> None:
    job = _job()
    assert job["env"]["NUMBA_CACHE_DIR"] == "${{ github.workspace }}/.numba-cache"
    install_at, install = _step(job, "Install kitti-eval")
    key_at, key = _step(job, "numba")
    cache_at, cache = _step(job, "actions/cache@v4")
    gate_at, _ = _step(job, "Evaluate and gate")
    assert install_at < key_at < cache_at < gate_at  # installed, named, restored, then used
    assert '"numba>=0.68"' in install["run"]  # numba stamps its cache with the sources' content from 0.68 on
    assert key["run"] == 'echo "key=$(python -m kitti_eval._jit --cache-key)" >> "$GITHUB_OUTPUT"'
    assert cache["with"] == {"path": "${{ env.NUMBA_CACHE_DIR }}", "key": "${{ steps.numba.outputs.key }}"}


def _python_env(site: Path | None = None, **extra: str) -> dict[str, str]:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}", **extra)
    if site is not None:
        env["PYTHONPATH"] = str(site)
    env.pop("NUMBA_DISABLE_JIT", None)
    return env


def _key_step(tmp_path: Path, env: dict[str, str]) -> str:
    """The job's 'Name numba's cache' step, run by bash as written; the key it gives actions/cache."""
    bash = shutil.which("bash")
    if bash is None:
        pytest.skip("no bash")
    output = tmp_path / "github-output"
    output.write_text("")
    script = _step(_job(), "numba")[1]["run"]
    proc = subprocess.run(
        [bash, "-c", "set -euo pipefail\n" + script],
        cwd=tmp_path,
        env=dict(env, GITHUB_OUTPUT=str(output)),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    lines = output.read_text().splitlines()
    assert len(lines) == 1 and lines[0].startswith("key="), lines
    return lines[0][4:]


def test_the_key_names_the_versions_and_changes_with_the_cpu(tmp_path: Path) -> None:
    from kitti_eval import _jit

    key = _key_step(tmp_path, _python_env())
    python = ".".join(map(str, sys.version_info[:3]))
    assert re.fullmatch(
        rf"kitti-eval-{kitti_eval.__version__}-numba-{numba.__version__}-py{python}-[0-9a-f]{{16}}", key
    )
    assert key == _jit.cache_key()  # the same in this process as in the job's shell
    # numba compiles for the CPU it runs on: another CPU model is another key, not a restored cache it ignores
    assert _key_step(tmp_path, _python_env(NUMBA_CPU_NAME="generic")) != key


def _install(site: Path, when: float) -> None:
    """The package copied as a fresh install writes it: every file new, all with the time ``when``."""
    shutil.rmtree(site, ignore_errors=True)
    shutil.copytree(PACKAGE, site / "kitti_eval", ignore=shutil.ignore_patterns("__pycache__"))
    for path in (site / "kitti_eval").rglob("*"):
        os.utime(path, (when, when))


def _run_counting(tmp_path: Path, site: Path, cache: Path) -> dict[str, Any]:
    env = _python_env(site, NUMBA_CACHE_DIR=str(cache))
    out = tmp_path / "demo.json"
    proc = subprocess.run(
        [sys.executable, "-c", _COUNT, str(out)], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = dict(json.loads(proc.stdout.splitlines()[-1]))
    assert result["code"] == 0 and Path(result["package"]).parent == site / "kitti_eval"
    ap = json.loads(out.read_text())["ap"]["strict"]["R40"]["Car"]["3d"]["moderate"]
    assert ap == pytest.approx(60.33954716517563, abs=1e-9)  # the demo's numbers, compiled or loaded
    return result


@pytest.mark.slow
@pytest.mark.skipif(numba.config.DISABLE_JIT, reason="NUMBA_DISABLE_JIT: nothing is compiled")
@pytest.mark.skipif(
    tuple(int(p) for p in numba.__version__.split(".")[:2]) < (0, 68),
    reason="numba before 0.68 stamps its cache with the sources' modification times (the job installs 0.68+)",
)
def test_a_restored_cache_compiles_nothing_after_a_fresh_install(tmp_path: Path) -> None:
    site, first_cache, restored = tmp_path / "site-packages", tmp_path / "cache-run-1", tmp_path / "cache-run-2"
    # run 1: a fresh install, an empty cache: everything is compiled, and the cache saved under its key
    _install(site, when=1_700_000_000)
    key = _key_step(tmp_path, _python_env(site))
    first = _run_counting(tmp_path, site, first_cache)
    assert len(first["compiled"]) > 20
    # run 2: installed again (other file times), the cache restored by that key: nothing is compiled
    _install(site, when=1_760_000_000)
    assert _key_step(tmp_path, _python_env(site)) == key
    shutil.copytree(first_cache, restored)
    second = _run_counting(tmp_path, site, restored)
    assert second["compiled"] == []
    # a kitti-eval whose sources differ is another key, so it never restores the older kernels
    with open(site / "kitti_eval" / "core" / "matching.py", "a") as fh:
        fh.write("\n# another version\n")
    assert _key_step(tmp_path, _python_env(site)) != key
