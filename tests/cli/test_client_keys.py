"""The client's saved state without a service (httpx's MockTransport answers): a submission's idempotency key
saved before its file is sent and sent again by the next run of the same file to the same phase until the
submission is shown scored (``new``: a new one); the token kept safely: its file written 0600 whatever was left
beside it, plain http refused to a host other than this machine, a missing token that names ``kitti-eval
login``."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from kitti_eval.cli import main
from kitti_eval.client import Client, Retries, save_token
from kitti_eval.client_state import FILE_NAME, PendingKeys
from kitti_eval.errors import ConfigError, QuotaExceeded, ServiceError

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden" / "small"
_JOB = {"id": "j1", "kind": "submission", "state": "queued", "position": 1, "submission": "j1"}
_SCORED = {"id": "j1", "benchmark": "b", "status": "scored", "scores": {"Car/3d/moderate/R40/strict": 80.0}}


class _Killed(BaseException):
    """The process killed where it stands: no handler of the client runs (as SIGKILL)."""


class _Service:
    """Answers each request with the next of ``script``; keeps what was sent."""

    def __init__(self, script: list[Callable[[httpx.Request], httpx.Response]]) -> None:
        self.script = list(script)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        return self.script.pop(0)(request)

    def keys(self) -> list[str]:
        return [r.headers["Idempotency-Key"] for r in self.requests if r.method == "POST"]


def _answer(code: int, body: Any) -> Callable[[httpx.Request], httpx.Response]:
    return lambda request: httpx.Response(code, json=body)


def _killed(request: httpx.Request) -> httpx.Response:
    raise _Killed


@pytest.fixture(autouse=True)
def config(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "client-config"
    monkeypatch.setenv("KITTI_EVAL_CONFIG_DIR", str(folder))
    monkeypatch.delenv("KITTI_EVAL_TOKEN", raising=False)
    monkeypatch.delenv("KITTI_EVAL_ALLOW_HTTP", raising=False)
    return folder


def _client(service: _Service, url: str = "https://service.test") -> Client:
    return Client(url, "tok", retries=Retries(within_s=0), transport=httpx.MockTransport(service))


def _submit(service: _Service, **kw: Any) -> Any:
    with _client(service) as c:
        return c.submit(GOLDEN / "result.pkl", "b", check=False, **kw)


def test_a_run_killed_after_its_file_was_accepted_is_answered_with_its_submission_when_run_again(config) -> None:
    service = _Service([_answer(202, _JOB), _killed])  # accepted, then killed while following its job
    with pytest.raises(_Killed):
        _submit(service)
    first = service.keys()[0]
    saved = json.loads((config / FILE_NAME).read_text())
    assert [v["key"] for v in saved.values()] == [first]
    assert stat.S_IMODE(os.stat(config / FILE_NAME).st_mode) == 0o600
    # the same file to the same phase: the saved key again, answered with the submission it made
    again = _Service([_answer(201, _SCORED)])
    submission = _submit(again)
    assert again.keys() == [first] and submission.reused and submission.id == "j1"
    assert json.loads((config / FILE_NAME).read_text()) == {}  # shown scored: forgotten
    after = _Service([_answer(201, _SCORED)])
    assert not _submit(after).reused and after.keys() != [first]


def test_new_sends_a_new_key_and_another_phase_or_file_has_its_own(config, tmp_path) -> None:
    service = _Service([_answer(202, _JOB), _killed])
    with pytest.raises(_Killed):
        _submit(service)
    first = service.keys()[0]
    new = _Service([_answer(201, _SCORED)])
    assert not _submit(new, new=True).reused
    assert new.keys()[0] != first
    other_phase = _Service([_answer(201, _SCORED)])
    _submit(other_phase, phase="test")
    assert other_phase.keys()[0] not in (first, new.keys()[0])
    assert other_phase.requests[0].url.path == "/v1/benchmarks/b/phases/test/submissions"


def test_no_wait_keeps_the_key_until_a_run_shows_the_submission_scored(config) -> None:
    service = _Service([_answer(202, _JOB)])
    _submit(service, wait=False)
    again = _Service([_answer(201, _SCORED)])
    assert _submit(again).reused and again.keys() == service.keys()
    assert json.loads((config / FILE_NAME).read_text()) == {}


def test_a_refusal_that_recorded_nothing_forgets_the_key(config) -> None:
    over = {"error": {"code": "quota_exceeded", "message": "used", "retry_at": "2030-01-01T00:00:00+00:00"}}
    with pytest.raises(QuotaExceeded):
        _submit(_Service([_answer(429, over)]))
    assert json.loads((config / FILE_NAME).read_text()) == {}


def test_a_given_key_is_sent_as_given_and_not_saved(config) -> None:
    service = _Service([_answer(202, _JOB), _killed])
    with pytest.raises(_Killed):
        _submit(service, idempotency_key="ci-run-7")
    assert service.keys() == ["ci-run-7"] and not (config / FILE_NAME).exists()


def test_a_saved_keys_file_that_is_not_ours_is_a_config_error(config) -> None:
    config.mkdir()
    (config / FILE_NAME).write_text("[1]")
    with pytest.raises(ConfigError, match="not the submissions' keys"):
        PendingKeys(config).get("https://s", "b", None, "0" * 64)


_SAVER = """
import sys
from pathlib import Path
from kitti_eval.client_state import PendingKeys

keys = PendingKeys(Path(sys.argv[1]))
for i in range(int(sys.argv[3])):
    keys.save("https://s", "b", None, f"{sys.argv[2]}-{i:04d}", f"key-{sys.argv[2]}-{i}")
"""


def test_two_runs_sharing_the_folder_lose_none_of_each_other_s_keys(config) -> None:
    """Two processes save keys into one folder at once: each save reads the file and writes it again, and
    without a lock one overwrites what the other has just saved."""
    n = 150
    runs = [
        subprocess.Popen([sys.executable, "-c", _SAVER, str(config), who, str(n)], stderr=subprocess.PIPE, text=True)
        for who in ("a", "b")
    ]
    for run in runs:
        assert run.wait(timeout=300) == 0, run.stderr.read() if run.stderr else ""
    saved = json.loads((config / FILE_NAME).read_text())
    keys = sorted(entry["key"] for entry in saved.values())
    assert keys == sorted(f"key-{who}-{i}" for who in ("a", "b") for i in range(n))


# ------------------------------------------------------------------------------------------ the token


def test_the_token_file_is_owner_only_whatever_was_left_or_planted_beside_it(config, tmp_path) -> None:
    config.mkdir()
    left = config / "services.json.partial"  # a leftover world-readable partial file, as an older writer left it
    left.write_text("{}")
    os.chmod(left, 0o644)
    target = tmp_path / "elsewhere.json"  # and a symlink planted where a partial file would go
    (config / ".services.json.partial").symlink_to(target)
    path = save_token("https://a", "secret")
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert json.loads(path.read_text()) == {"https://a": "secret"}
    assert not target.exists() and left.read_text() == "{}"
    save_token("https://b", "other")
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert sorted(p.name for p in config.iterdir()) == [".services.json.partial", "services.json", left.name]


@pytest.mark.parametrize(
    ("url", "sent"),
    [
        ("http://127.0.0.1:8000", True),
        ("http://localhost:8000", True),
        ("http://[::1]:8000", True),
        ("https://10.1.2.3:8000", True),
        ("http://10.1.2.3:8000", False),
        ("http://kitti.example.org", False),
    ],
)
def test_plain_http_carries_the_token_to_this_machine_only(url, sent, monkeypatch) -> None:
    if sent:
        Client(url, "tok").close()
    else:
        with pytest.raises(ConfigError, match="unencrypted.*--allow-http"):
            Client(url, "tok")
        Client(url, "tok", allow_http=True).close()
        monkeypatch.setenv("KITTI_EVAL_ALLOW_HTTP", "1")
        Client(url, "tok").close()
    Client(url).close()  # without a token nothing is at stake


def test_http_to_another_host_is_refused_by_the_commands_unless_allowed(capsys, monkeypatch) -> None:
    args = ["submit", str(GOLDEN / "result.pkl"), "--benchmark", "b", "--service", "http://10.1.2.3:9"]
    monkeypatch.setenv("KITTI_EVAL_TOKEN", "tok")
    assert main(args) == 2
    assert "unencrypted" in capsys.readouterr().err
    main([*args, "--allow-http", "--retry-for", "0"])  # allowed: sent (whatever answers there)
    assert "unencrypted" not in capsys.readouterr().err


def test_a_missing_token_names_kitti_eval_login() -> None:
    refusal = {"error": {"code": "unauthorized", "message": "sign in: send 'Authorization: Bearer <token>'"}}
    service = _Service([_answer(401, refusal)])
    with Client("https://service.test", transport=httpx.MockTransport(service)) as c:
        with pytest.raises(ServiceError, match="kitti-eval login --service https://service.test") as e:
            c.teams("b")
    assert e.value.status == 401
