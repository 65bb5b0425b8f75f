"""The service's client without a service (httpx's MockTransport answers): what is sent again and how long it
waits, the one idempotency key of a submission across its retries, the refusals as errors of the one tree, the
saved token, and the exit codes the commands turn them into."""

from __future__ import annotations

import json
import os
import random
import stat
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import pytest

from kitti_eval import client as client_module
from kitti_eval.cli import main
from kitti_eval.client import Client, Retries, save_token, saved_token, token_for
from kitti_eval.errors import ConfigError, QuotaExceeded, ServiceError, ServiceUnreachable, SubmissionRefused

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden" / "small"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def _own_config_folder(tmp_path, monkeypatch) -> None:
    """The client's folder (saved tokens and submissions' keys) is the test's own."""
    monkeypatch.setenv("KITTI_EVAL_CONFIG_DIR", str(tmp_path / "client-config"))


class _Answers:
    """A scripted service: each request is recorded and answered by the next function of ``script``."""

    def __init__(self, script: list[Callable[[httpx.Request], httpx.Response]]) -> None:
        self.script = list(script)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        request.read()
        self.requests.append(request)
        return self.script.pop(0)(request)


def _status(code: int, body: Any = None, **headers: str) -> Callable[[httpx.Request], httpx.Response]:
    return lambda request: httpx.Response(code, json=body if body is not None else {}, headers=headers)


def _drop(request: httpx.Request) -> httpx.Response:
    raise httpx.RemoteProtocolError("Server disconnected without sending a response.", request=request)


def _client(answers: _Answers, sleeps: list[float], monkeypatch, **retries: Any) -> Client:
    monkeypatch.setattr(client_module.time, "sleep", sleeps.append)
    policy = Retries(rng=random.Random(0), **retries)
    return Client("https://service.test", "tok", retries=policy, transport=httpx.MockTransport(answers))


_JOB = {"id": "j1", "kind": "submission", "state": "queued", "position": 1, "submission": "j1"}
_SCORED = {"id": "j1", "benchmark": "b", "status": "scored", "scores": {"Car/3d/moderate/R40/strict": 80.1234}}


def test_a_submission_sent_again_carries_its_one_key_and_honours_retry_after(monkeypatch) -> None:
    answers = _Answers(
        [
            _drop,
            _status(503, {"error": {"code": "busy", "message": "busy"}}, **{"Retry-After": "7"}),
            _status(429, {"error": {"code": "too_many_queued", "message": "wait"}}, **{"Retry-After": "2"}),
            _status(202, _JOB),
            _status(200, {**_JOB, "state": "done", "result_location": "/v1/benchmarks/b/submissions/j1"}),
            _status(200, _SCORED),
        ]
    )
    sleeps: list[float] = []
    with _client(answers, sleeps, monkeypatch) as c:
        submission = c.submit(GOLDEN / "result.pkl", "b", check=False)
    assert submission.status == "scored" and submission.scores == {"Car/3d/moderate/R40/strict": 80.1234}
    posts = [r for r in answers.requests if r.method == "POST"]
    assert len(posts) == 4
    keys = {r.headers["Idempotency-Key"] for r in posts}
    assert len(keys) == 1 and len(keys.pop()) == 36
    assert all(GOLDEN.joinpath("result.pkl").read_bytes() in r.content for r in posts)  # the whole file each time
    assert all(r.headers["Authorization"] == "Bearer tok" for r in answers.requests)
    assert 0.05 <= sleeps[0] <= 0.5  # no Retry-After: full jitter below the first step
    assert 7 <= sleeps[1] <= 7.7 and 2 <= sleeps[2] <= 2.2  # Retry-After plus up to a tenth
    assert [r.url.path for r in answers.requests[4:]] == ["/v1/jobs/j1", "/v1/benchmarks/b/submissions/j1"]


def _sent_file(request: httpx.Request) -> bytes:
    """The bytes of the one file of a multipart request."""
    boundary = request.headers["content-type"].split("boundary=")[1].encode()
    (part,) = [p for p in request.content.split(b"--" + boundary) if b"filename=" in p]
    return part.split(b"\r\n\r\n", 1)[1][: -len(b"\r\n")]


def test_a_folder_sent_again_is_the_same_file_so_its_key_is_not_refused_as_reused(tmp_path, monkeypatch) -> None:
    # a folder is packed again for each try: a try whose answer was lost may have been recorded with its key,
    # and the service refuses the key with another file (gzip's header once held the time of packing)
    import io
    import tarfile

    folder = tmp_path / "pred"
    folder.mkdir()
    for frame in ("000000", "000001"):
        folder.joinpath(f"{frame}.txt").write_text("Car 0 0 0 0 0 10 10 1.5 1.6 3.9 1 1.7 20 0 0.9\n")
    clock = iter(range(1_800_000_000, 1_800_000_000 + 1000, 100))
    monkeypatch.setattr(client_module.time, "time", lambda: float(next(clock)))  # a minute or more between tries
    answers = _Answers([_drop, _status(201, _SCORED)])
    with _client(answers, [], monkeypatch) as c:
        c.submit(folder, "b", check=False)
    first, again = (_sent_file(r) for r in answers.requests)
    assert first == again and first[:2] == b"\x1f\x8b"  # one gzip, byte for byte
    assert {r.headers["Idempotency-Key"] for r in answers.requests} == {answers.requests[0].headers["Idempotency-Key"]}
    with tarfile.open(fileobj=io.BytesIO(first)) as tar:
        assert tar.getnames() == ["000000.txt", "000001.txt"]


def test_two_submissions_draw_two_keys(monkeypatch) -> None:
    answers = _Answers([_status(201, _SCORED), _status(201, _SCORED)])
    with _client(answers, [], monkeypatch) as c:
        c.submit(GOLDEN / "result.pkl", "b", check=False)
        c.submit(GOLDEN / "result.pkl", "b", check=False)
    assert answers.requests[0].headers["Idempotency-Key"] != answers.requests[1].headers["Idempotency-Key"]


def test_a_service_away_past_the_retry_time_is_unreachable(monkeypatch) -> None:
    answers = _Answers([_status(503, {"error": {"code": "database_unavailable", "message": "down"}})] * 100)
    sleeps: list[float] = []
    clock = [0.0]

    def sleep(s: float) -> None:
        sleeps.append(s)
        clock[0] += s

    with _client(answers, sleeps, monkeypatch, within_s=60, max_s=10) as c:
        monkeypatch.setattr(client_module.time, "sleep", sleep)
        monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
        with pytest.raises(ServiceUnreachable, match=r"within 60 s \(\d+ tries; the last: 503 database_unavailable\)"):
            c.benchmarks()
    assert sum(sleeps) <= 60 and len(sleeps) >= 6
    assert max(sleeps) <= 10  # the backoff is capped
    assert sleeps[:3] != sorted(sleeps[:3]) or len(set(sleeps)) == len(sleeps)  # drawn, not a fixed ladder


@pytest.mark.parametrize(
    ("status", "error", "kind", "code"),
    [
        (429, {"code": "quota_exceeded", "message": "used", "retry_at": "2030-01-01T00:00:00+00:00"}, QuotaExceeded, 4),
        (422, {"code": "invalid_submission", "message": "bad", "problems": ["a", "b"]}, SubmissionRefused, 1),
        (422, {"code": "unsafe_pickle", "message": "refused"}, ServiceError, 1),
        (404, {"code": "not_found", "message": "no benchmark b"}, ServiceError, 2),
        (401, {"code": "unauthorized", "message": "no token"}, ServiceError, 2),
    ],
)
def test_a_refusal_is_not_sent_again_and_is_an_error_of_the_tree(monkeypatch, status, error, kind, code) -> None:
    from kitti_eval.cli.remote import exit_code

    answers = _Answers([_status(status, {"error": error})])
    with _client(answers, [], monkeypatch) as c, pytest.raises(kind) as raised:
        c.submit(GOLDEN / "result.pkl", "b", check=False)
    assert len(answers.requests) == 1
    assert type(raised.value) is kind and raised.value.status == status and raised.value.code == error["code"]
    assert raised.value.message == error["message"]
    assert exit_code(raised.value) == code
    if kind is QuotaExceeded:
        assert raised.value.retry_at == "2030-01-01T00:00:00+00:00"
    if kind is SubmissionRefused:
        assert raised.value.problems == ["a", "b"]


def test_a_job_that_failed_raises_its_error(monkeypatch) -> None:
    failed = {**_JOB, "state": "failed", "error": {"status": 422, "code": "invalid_input", "message": "frame 7: NaN"}}
    answers = _Answers([_status(202, _JOB), _status(200, failed)])
    with _client(answers, [], monkeypatch) as c, pytest.raises(ServiceError, match="job j1 failed: frame 7: NaN") as e:
        c.submit(GOLDEN / "result.pkl", "b", check=False)
    assert e.value.refused_input


def test_the_token_is_the_argument_else_the_environment_else_the_saved_one(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("KITTI_EVAL_CONFIG_DIR", str(tmp_path / "cfg"))
    monkeypatch.delenv("KITTI_EVAL_TOKEN", raising=False)
    assert token_for("http://a") is None
    path = save_token("http://a/", "saved")
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o600
    assert saved_token("http://a") == "saved" and saved_token("http://b") is None
    assert token_for("http://a") == "saved"
    monkeypatch.setenv("KITTI_EVAL_TOKEN", "from-env")
    assert token_for("http://a") == "from-env"
    assert token_for("http://a", "given") == "given"
    path.write_text("[1, 2]")
    with pytest.raises(ConfigError, match="not the tokens kitti-eval login writes"):
        saved_token("http://a")


def test_a_service_url_that_is_not_http_is_a_usage_error() -> None:
    with pytest.raises(ConfigError, match="expected http"):
        Client("ftp://x")
    assert main(["submit", str(GOLDEN / "result.pkl"), "--benchmark", "b", "--service", "x"]) == 2


def test_the_library_imports_without_httpx() -> None:
    """httpx and filelock are the client extra's: the evaluator, the CLI and its help work without them."""
    code = (
        "import sys; sys.modules['httpx'] = None; sys.modules['filelock'] = None\n"
        "import kitti_eval, kitti_eval.client, kitti_eval.cli\n"
        "from kitti_eval.cli import build_parser; build_parser()\n"
        "try:\n    kitti_eval.client.Client('http://x')\nexcept kitti_eval.errors.ConfigError as e:\n    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True).stdout
    assert "the client needs httpx: pip install 'kitti-eval[client]'" in out


def test_scores_as_table_and_markdown() -> None:
    from kitti_eval.cli.submit import render_submission
    from kitti_eval.client import Submission

    view = {**_SCORED, "scores": {"Car/3d/moderate/R40/strict": 80.1234, "Car/3d/hard/R40/strict": None}}
    sub = Submission.from_body({**view, "scored_on": "public"})
    table = render_submission(sub, "table", key=["Car/3d/moderate/R40/strict"])
    assert table.splitlines() == [
        "submission j1 to b: scored, on the public part of the test set",
        "key                          80.1234  (Car/3d/moderate/R40/strict)",
        "Car/3d/moderate/R40/strict   80.1234",
        "Car/3d/hard/R40/strict             -",
    ]
    md = render_submission(sub, "markdown", key=["Car/3d/moderate/R40/strict"])
    assert "| **key** (Car/3d/moderate/R40/strict) | **80.12** |" in md and "| Car/3d/hard/R40/strict |  |" in md
    assert json.loads(render_submission(sub, "json")) == {**view, "scored_on": "public"}


def test_the_token_never_follows_an_answer_to_another_host(monkeypatch) -> None:
    """A result's place is a path of the service's own: an absolute URL in an answer is refused, not fetched."""
    done = {"id": "j1", "kind": "evaluation", "state": "done", "result_location": "http://elsewhere.test/steal"}
    answers = _Answers([_status(202, {**_JOB, "kind": "evaluation"}), _status(200, done)])
    with _client(answers, [], monkeypatch) as c, pytest.raises(ServiceError, match="not a path of its own"):
        c.evaluate(GOLDEN / "result.pkl", "small")
    assert {r.url.host for r in answers.requests} == {"service.test"} and len(answers.requests) == 2


@pytest.mark.parametrize(
    "answer",
    [
        lambda request: httpx.Response(200, text="<html>a proxy's page</html>"),
        _status(200, {"something": "else"}),
        _status(200, [1, 2, 3]),
    ],
)
def test_an_answer_that_is_not_the_services_is_an_error_of_the_tree(monkeypatch, answer) -> None:
    answers = _Answers([answer])
    with _client(answers, [], monkeypatch) as c, pytest.raises(ServiceError, match="an answer this client cannot read"):
        c.quota("b")


def test_a_services_text_is_shown_without_its_control_characters(monkeypatch) -> None:
    """A hostile service's message cannot drive the terminal (escape sequences) nor flood it."""
    message = "no\x1b[2J\x1b]0;owned\x07 way" + "x" * 5000
    answers = _Answers([_status(404, {"error": {"code": "not_found\x1b[31m", "message": message}})])
    with _client(answers, [], monkeypatch) as c, pytest.raises(ServiceError) as e:
        c.benchmark("b")
    assert e.value.message.startswith("no?[2J?]0;owned? way") and len(e.value.message) == 2003
    assert e.value.code == "not_found?[31m"


def test_service_takes_the_name_of_a_registered_ground_truth_not_a_file(capsys) -> None:
    pred = str(GOLDEN / "result.pkl")
    code = main(["--service", "http://127.0.0.1:9", "--gt", str(GOLDEN / "kitti_infos_val.pkl"), "--pred", pred])
    assert code == 2
    assert "with --service, --gt names a ground truth registered on the service" in capsys.readouterr().err


def test_an_id_from_an_answer_goes_into_no_path_unless_it_is_an_id(monkeypatch) -> None:
    answers = _Answers([_status(202, {**_JOB, "id": "../../admin/users"})])
    with _client(answers, [], monkeypatch) as c, pytest.raises(ServiceError, match="cannot read"):
        c.submit(GOLDEN / "result.pkl", "b", check=False)
    assert len(answers.requests) == 1


def _no_home(monkeypatch) -> None:
    """As under ``env -i`` with a uid that /etc/passwd does not list (a container's ``--user 12345``)."""
    import pwd

    for name in ("HOME", "XDG_CONFIG_HOME", "KITTI_EVAL_CONFIG_DIR"):
        monkeypatch.delenv(name, raising=False)

    def unknown(uid: int) -> Any:
        raise KeyError(f"getpwuid(): uid not found: {uid}")

    monkeypatch.setattr(pwd, "getpwuid", unknown)


def test_without_a_home_the_saved_tokens_folder_is_a_sentence_naming_the_settings(tmp_path, monkeypatch) -> None:
    _no_home(monkeypatch)
    with pytest.raises(ConfigError, match=r"HOME is not set .* set KITTI_EVAL_CONFIG_DIR to a folder it may write"):
        save_token("http://a", "t")
    with pytest.raises(ConfigError, match="KITTI_EVAL_CONFIG_DIR"):
        token_for("http://a")
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg"))
    assert save_token("http://a", "t") == tmp_path / "xdg" / "kitti-eval" / "services.json"
    monkeypatch.setenv("KITTI_EVAL_CONFIG_DIR", str(tmp_path / "own"))
    assert save_token("http://a", "t") == tmp_path / "own" / "services.json"
    assert saved_token("http://a") == "t"


def test_login_without_a_home_exits_2_with_the_sentence_before_asking_the_service(monkeypatch, capsys) -> None:
    import io

    _no_home(monkeypatch)
    monkeypatch.setattr(sys, "stdin", io.StringIO("tok\n"))
    assert main(["login", "--service", "http://127.0.0.1:9", "--retry-for", "0"]) == 2
    err = capsys.readouterr().err
    assert "kitti-eval: error: the client has no folder for its saved tokens" in err
    assert "KITTI_EVAL_CONFIG_DIR" in err and "Traceback" not in err


def test_an_evaluation_not_kept_goes_to_the_gates_route_and_is_read_once_from_its_job(monkeypatch) -> None:
    """keep=False: sent to /v1/gates/evaluations (no labels, no project: nothing stores them), followed through its
    job to the result's place, read there once; the same key is sent with every try."""
    doc = {"id": "j1", "ap": {}, "evaluation": {"kept": False}}
    done = {"id": "j1", "kind": "gate", "state": "done", "result_location": "/v1/gates/evaluations/j1"}
    answers = _Answers([_drop, _status(202, {**_JOB, "kind": "gate"}), _status(200, done), _status(200, doc)])
    with _client(answers, [], monkeypatch) as c:
        evaluation = c.evaluate(GOLDEN / "result.pkl", "small", keep=False, errors=True)
        with pytest.raises(ConfigError, match="takes no labels nor project"):
            c.evaluate(GOLDEN / "result.pkl", "small", keep=False, labels={"branch": "x"})
    assert (evaluation.id, evaluation.document, evaluation.meta) == ("j1", {"ap": {}}, {"kept": False})
    sent = [(r.method, r.url.path) for r in answers.requests]
    assert sent == [
        ("POST", "/v1/gates/evaluations"),
        ("POST", "/v1/gates/evaluations"),
        ("GET", "/v1/jobs/j1"),
        ("GET", "/v1/gates/evaluations/j1"),
    ]
    keys = {r.headers["Idempotency-Key"] for r in answers.requests[:2]}
    assert len(keys) == 1 and b'name="errors"\r\n\r\ntrue' in answers.requests[0].content
