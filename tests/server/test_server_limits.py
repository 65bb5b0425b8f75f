"""The limits a hostile client meets in process: one 413 code, echoed input cut short, bounded parameters."""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
from server_helpers import ADMIN, assert_error, golden_bytes, upload

CAP_MB = 1
OVER_CAP = b"\x80\x04" + b"\0" * (CAP_MB << 20)


@pytest.fixture(scope="module")
def client(service_client):
    with service_client(max_upload_mb=CAP_MB) as c:
        yield c


def multipart(fields: dict[str, bytes], files: dict[str, tuple[str, bytes]]) -> tuple[bytes, str]:
    """A multipart/form-data body built by hand, so field values can be any bytes (not only UTF-8 text)."""
    boundary = "limits-boundary-7d0c"
    parts = [
        f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"\r\n\r\n'.encode() + v + b"\r\n"
        for k, v in fields.items()
    ]
    parts += [
        f'--{boundary}\r\nContent-Disposition: form-data; name="{k}"; filename="{name}"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n".encode()
        + data
        + b"\r\n"
        for k, (name, data) in files.items()
    ]
    parts.append(f"--{boundary}--\r\n".encode())
    return b"".join(parts), f"multipart/form-data; boundary={boundary}"


def chunked(body: bytes, size: int = 64 * 1024) -> Iterator[bytes]:
    """The body as a stream without Content-Length: the cap must hold while it arrives."""
    for i in range(0, len(body), size):
        yield body[i : i + size]


# ------------------------------------------------------------------------------------------------- 413


@pytest.mark.parametrize(
    ("path", "headers", "files"),
    [
        ("/v1/evaluations", {}, {"predictions": ("r.pkl", OVER_CAP)}),
        ("/v1/ground-truths", ADMIN, {"file": ("infos.pkl", OVER_CAP)}),
    ],
)
def test_every_413_has_the_one_code_declared_or_streamed(client, path, headers, files) -> None:
    body, ctype = multipart({"gt": b"demo", "name": b"big"}, files)
    declared = client.post(path, content=body, headers={**headers, "content-type": ctype})
    streamed = client.post(path, content=chunked(body), headers={**headers, "content-type": ctype})
    assert "content-length" not in streamed.request.headers
    for response in (declared, streamed):
        err = assert_error(response, 413, "upload limit of 1 MB", "KITTI_EVAL_MAX_UPLOAD_MB")
        assert err["code"] == "payload_too_large"
    assert upload(client, golden_bytes("result.pkl")).status_code == 201


def test_a_json_body_over_the_cap_is_the_same_413(client) -> None:
    body = b'{"evaluation": "' + b"x" * (CAP_MB << 20) + b'"}'
    for content in (body, chunked(body)):
        response = client.post("/v1/gates", content=content, headers={"content-type": "application/json"})
        assert assert_error(response, 413, "upload limit")["code"] == "payload_too_large"


# ------------------------------------------------------------------------------------------ echoed input

HUGE = "A" * 60_000


def assert_short_error(response, status: int | tuple[int, ...], length: str = "(60000 characters)") -> dict:
    """A 4xx JSON error that quotes the client's 60 kB value only in part, and says how long it was (the value
    quoted by the service, or the whole message when the library quoted it)."""
    err = assert_error(response, status)
    assert len(response.content) < 2000, (len(response.content), response.text[:300])
    assert "AAAA" in err["message"] and "…" in err["message"], err["message"][:300]
    assert length in err["message"], err["message"][-300:]
    return err


@pytest.mark.parametrize("field", ["classes", "threshold_sets", "ranges", "iou"])
def test_a_huge_evaluation_option_is_quoted_in_part(client, field) -> None:
    # the library quotes the bad value (twice, for a class name): the error body cuts the message
    response = upload(client, golden_bytes("result.pkl"), fields={field: HUGE})
    err = assert_short_error(response, 422, "characters in all)")
    assert len(err["message"]) < 1100


@pytest.mark.parametrize(
    "request_args",
    [
        ("POST", "/v1/evaluations", {"label": HUGE}),  # a label without '='
        ("POST", "/v1/evaluations", {"label": HUGE + "=1"}),  # a key that is not a label key
        ("GET", "/v1/evaluations", {"label": HUGE}),
        ("GET", "/v1/evaluations/some-id", {"format": HUGE}),
        ("GET", f"/v1/evaluations/{HUGE}", {}),
        ("GET", f"/v1/ground-truths/{HUGE}", {}),
        ("DELETE", f"/v1/ground-truths/{HUGE}", {}),
    ],
    ids=["label-form", "label-key", "label-query", "format", "evaluation-id", "ground-truth", "delete"],
)
def test_a_huge_form_path_or_query_value_is_quoted_in_part(client, request_args) -> None:
    method, path, values = request_args
    if method == "POST":
        response = upload(client, golden_bytes("result.pkl"), fields=values)
    else:
        response = client.request(method, path, params=values, headers=ADMIN)
    assert_short_error(response, (404, 422))


def test_a_huge_frame_id_is_quoted_in_part(client) -> None:
    evaluation = upload(client, golden_bytes("result.pkl")).json()["id"]
    response = client.get(f"/v1/frames/{'9' * 60_000}", params={"evaluation": evaluation})
    err = assert_error(response, 404)
    assert len(response.content) < 2000 and "60000 characters in all" in err["message"], response.text[:300]
    response = client.get(f"/v1/evaluations/{evaluation}/frames", params={"class": HUGE})
    assert_short_error(response, 422, "characters in all)")


@pytest.mark.parametrize(
    ("method", "path", "field"),
    [
        ("POST", "/ui/evaluations", "model"),  # the home page re-fills the form and says what is wrong
        ("GET", "/evaluations/{id}", "cls"),  # the worst-frames section says why it is empty
        ("GET", "/frames/000001", "score"),
        ("GET", "/frames/000001", "cls"),
        ("GET", "/evaluations/{huge}", None),
    ],
)
def test_web_pages_quote_a_huge_value_in_part(client, method, path, field) -> None:
    evaluation = upload(client, golden_bytes("result.pkl")).json()["id"]
    path = path.format(id=evaluation, huge=HUGE)

    def page(value: str):
        if method == "POST":
            form = {"gt": "demo", field: value}
            files = {"predictions": ("result.pkl", golden_bytes("result.pkl"))}
            return client.post(path, data=form, files=files, follow_redirects=False)
        return client.get(path, params={"e": evaluation, field: value} if field else {})

    huge = page(HUGE)
    small = page("B" * 300)  # as wrong, but short
    assert huge.status_code < 500 and huge.status_code == small.status_code, huge.text[:300]
    assert huge.headers["content-type"].startswith("text/html")
    assert len(huge.content) < len(small.content) + 3000, (len(huge.content), len(small.content))
    assert re.search(r"… \((60000|\d+ characters in all)", huge.text), huge.text[-500:]


# ------------------------------------------------------------------------------------------ bounded numbers


@pytest.mark.parametrize("score", ["nan", "inf", "-inf", "1e400", str(2**63), "-" + "9" * 400, "abc", "%ff"])
def test_the_frame_page_refuses_a_score_that_is_no_bounded_number(client, score) -> None:
    evaluation = upload(client, golden_bytes("result.pkl")).json()["id"]
    page = client.get(f"/frames/000001?e={evaluation}&score={score}")
    assert page.status_code == 422, page.text[:300]
    assert page.headers["content-type"].startswith("text/html")
    assert "score threshold must be a number between -1e+09 and 1e+09" in page.text
    assert client.get(f"/frames/000001?e={evaluation}&score=0.5").status_code == 200


# --------------------------------------------------------------------------------------- limits on work

_LABEL = b"Car 0.00 0 -1.58 587.01 173.33 614.12 200.12 1.65 1.67 3.64 -0.65 1.71 46.70 -1.59"


def test_many_boxes_in_few_bytes_are_refused_413_naming_the_frame(client, monkeypatch: pytest.MonkeyPatch) -> None:
    """One line repeated: a small tar.gz inside every byte limit that holds more boxes than a frame may."""
    import time

    from server_helpers import tar_of

    monkeypatch.setenv("KITTI_EVAL_MAX_BOXES_PER_FRAME", "500")
    frames = {f"pred/{i:06d}.txt": (_LABEL + b" 0.9\n") * 2000 for i in range(8)}
    started = time.monotonic()
    r = upload(client, tar_of(frames), "pred.tar.gz", gt="demo")
    err = assert_error(r, 413, "2000 boxes in one frame, more than the limit of 500", "KITTI_EVAL_MAX_BOXES_PER_FRAME")
    assert err["code"] == "over_work_limit" and err["frame"] == "000000"
    assert "pred.tar.gz:pred/000000.txt" in err["message"]
    assert time.monotonic() - started < 10
    assert client.get("/readyz").status_code == 200


def test_a_frame_whose_overlaps_pass_the_budget_is_refused_before_they_are_computed(
    client, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A writer's own ground truth: both sides of a frame theirs, the overlaps growing with the square."""
    from server_helpers import zip_of

    monkeypatch.setenv("KITTI_EVAL_MAX_FRAME_PAIRS", "10000")
    gt = zip_of({"label_2/000000.txt": (_LABEL + b"\n") * 300})
    pred = zip_of({"pred/000000.txt": (_LABEL + b" 0.9\n") * 300})
    r = upload(client, pred, "pred.zip", gt=None, gt_file=("label_2.zip", gt))
    err = assert_error(r, 413, "300 detections x 300 ground-truth boxes = 90000 overlaps in one frame", "10000")
    assert err["code"] == "over_work_limit" and err["frame"] == "000000"
    monkeypatch.setenv("KITTI_EVAL_MAX_FRAME_PAIRS", "90000")
    assert upload(client, pred, "pred.zip", gt=None, gt_file=("label_2.zip", gt)).status_code == 201


@pytest.mark.parametrize(
    ("env", "value"),
    [("KITTI_EVAL_MAX_BOXES", "lots"), ("KITTI_EVAL_MAX_FRAME_PAIRS", "0"), ("KITTI_EVAL_MAX_FRAMES", "-1")],
)
def test_a_limit_that_is_not_a_number_refuses_the_start(tmp_path, monkeypatch, env: str, value: str) -> None:
    """Said once, at the start, not as every job's failure."""
    from server_helpers import app_client

    from kitti_eval_server.errors import StartupRefused

    monkeypatch.setenv(env, value)
    with pytest.raises(StartupRefused) as refused, app_client(tmp_path / "data", warmup=False):
        pass
    assert f"{env}={value!r}: expected a number > 0 (a limit on input or work)" in refused.value.message
