"""An upload kept as it is: its bytes whole and hashed once, from memory or from the disk the form parser spooled
it to, wherever the file's position was left."""

from __future__ import annotations

import hashlib
import io
import os
from tempfile import SpooledTemporaryFile

import pytest

from kitti_eval_server.scoring.uploads import receive_content

MB = 1 << 20


def _spooled(content: bytes, max_size: int) -> SpooledTemporaryFile:
    f = SpooledTemporaryFile(max_size=max_size)
    for i in range(0, len(content), 64 * 1024):
        f.write(content[i : i + 64 * 1024])
    return f


@pytest.mark.parametrize("where", ["bytesio", "spooled in memory", "spooled to disk"])
def test_an_upload_is_received_whole_with_its_sha256(where) -> None:
    content = os.urandom(3 * MB + 17)
    file = io.BytesIO(content) if where == "bytesio" else _spooled(content, 64 * MB if "memory" in where else MB)
    file.seek(1234)  # wherever the parser left it
    received = receive_content(file, "dir/result.pkl", "predictions")
    assert received.content == content and received.size == len(content)
    assert received.sha256 == hashlib.sha256(content).hexdigest() and received.filename == "result.pkl"
    if where == "spooled in memory":  # handed over, not copied: the file's own buffer
        assert received.content is file._file.getvalue()
    file.close()
    assert received.content == content  # still whole once the upload is closed
