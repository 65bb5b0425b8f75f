"""The limits a hostile client meets in process: one 413 code, echoed input cut short, bounded parameters."""

from __future__ import annotations

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
