"""``kitti-eval admin invite add|list|revoke`` and ``kitti-eval admin user import``: links that make accounts for a
benchmark, and many accounts at once, all or nothing; what they make is what the service then admits."""

from __future__ import annotations

import csv
import io
from datetime import datetime, timedelta, timezone

import pytest
from server_accounts import bearer
from server_helpers import ADMIN, GOLDEN, app_client

from kitti_eval.cli import main


@pytest.fixture
def admin(tmp_path, monkeypatch, capsys):
    """Runs ``kitti-eval admin ...`` against the data folder ``tmp_path/data``: (exit code, stdout, stderr)."""
    for key in ("KITTI_EVAL_DATABASE_URL", "KITTI_EVAL_AUTH"):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv("KITTI_EVAL_DATA_DIR", str(tmp_path / "data"))

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(["admin", "--create", *argv])
        out, err = capsys.readouterr()
        return code, out, err

    return run


def _benchmark(admin) -> None:
    for argv in (
        ("project", "add", "class"),
        ("project", "add", "staff"),
        ("ground-truth", "add", "test-set", str(GOLDEN / "kitti_infos_val.pkl"), "--project", "class", "--sealed"),
        ("ground-truth", "add", "staff-gt", str(GOLDEN / "kitti_infos_val.pkl"), "--project", "staff"),
        ("benchmark", "add", "bench", "--ground-truth", "test-set"),
    ):
        assert admin(*argv)[0] == 0, argv


def test_an_invitation_from_the_cli_is_listed_with_the_accounts_it_made_and_revoked(admin, tmp_path) -> None:
    _benchmark(admin)
    code, out, _ = admin("invite", "add", "--benchmark", "bench", "--uses", "2", "--url", "https://eval.example/")
    assert code == 0 and "members of class" in out and "2 use(s)" in out
    # without --expires-days it expires in 14 days, and says when
    expires = datetime.fromisoformat(out.split("expires ")[1].split(",")[0])
    assert abs(expires - datetime.now(timezone.utc) - timedelta(days=14)) < timedelta(minutes=5)
    link = out.splitlines()[-1]
    assert link.startswith("https://eval.example/join/")
    code_ = link.rsplit("/", 1)[1]
    invitation_id = out.split()[1]
    with app_client(tmp_path / "data", auth="accounts") as c:
        assert c.post(f"/v1/join/{code_}", json={"name": "amy"}).status_code == 201
    code, out, _ = admin("invite", "list")
    assert code == 0
    assert out.splitlines() == [f"{invitation_id}\tbench\topen\tleft 1\texpires {expires.isoformat()}\tamy"]
    assert admin("invite", "revoke", invitation_id)[0] == 0
    assert admin("invite", "list")[1].split("\t")[2] == "revoked"
    code, _, err = admin("invite", "revoke", invitation_id)
    assert code == 1 and "no invitation" in err
    code, out, _ = admin("invite", "add", "--benchmark", "bench", "--expires-days", "2")
    assert code == 0 and "any number of uses" in out
    expires = datetime.fromisoformat(out.split("expires ")[1].split(",")[0])
    assert abs(expires - datetime.now(timezone.utc) - timedelta(days=2)) < timedelta(minutes=5)
    code, _, err = admin("invite", "add", "--benchmark", "nope")
    assert code == 1 and "no benchmark named 'nope'" in err
    code, _, err = admin("invite", "add", "--benchmark", "bench", "--uses", "0")
    assert code == 1 and "at least once" in err
    code, _, err = admin("invite", "add", "--benchmark", "bench", "--project", "staff")
    assert code == 1 and "members of 'class'" in err
    audit = admin("audit")[1]
    assert "invitation.add" in audit and "invitation.revoke" in audit and "invitation.join" in audit


def test_an_import_of_three_lines_prints_three_working_tokens(admin, tmp_path) -> None:
    _benchmark(admin)
    (tmp_path / "people.csv").write_text("name,project\nann,class\nben,class\ncid,\n")
    code, out, err = admin("user", "import", str(tmp_path / "people.csv"))
    assert code == 0, err
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [r["name"] for r in rows] == ["ann", "ben", "cid"] and all(r["token"].startswith("kte_") for r in rows)
    with app_client(tmp_path / "data", auth="accounts") as c:
        for r in rows:
            assert c.get("/v1/me", headers=bearer(r["token"])).json()["user"] == r["name"]
        users = {u["name"]: u["projects"] for u in c.get("/v1/admin/users", headers=ADMIN).json()["items"]}
        assert users == {"ann": ["class"], "ben": ["class"], "cid": []}
        assert c.get("/v1/benchmarks/bench", headers=bearer(rows[0]["token"])).status_code == 200
        assert c.get("/v1/ground-truths/staff-gt", headers=bearer(rows[0]["token"])).status_code == 404
        audit = c.get("/v1/admin/audit", headers=ADMIN).json()["items"]
        imported = sorted(r["target"].split()[0] for r in audit if r["action"] == "user.import")
        assert imported == ["ann", "ben", "cid"]


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("name,project\ndee,class\nann,class\n", "line 3: a user named 'ann' exists"),
        ("name,project\ndee,class\nbad name,class\n", "line 3: user name 'bad name' is not valid"),
        ("name\ndee\ndee\n", "line 3: the user 'dee' is on line 2 too"),
        ("name,project\ndee,nope\n", "line 2: no project named 'nope'"),
        ("user,project\ndee,class\n", "line 1: the columns are name"),
        ("name\ndee\nanyone\n", "line 3: the user name 'anyone' is reserved"),
        ("name\ndee\nAdmin\n", "line 3: the user name 'Admin' is reserved"),
        ("name\ndee\nANN\n", "line 3: a user named 'ANN' exists"),  # ann's, ignoring case
        ("name\ndee\nDee\n", "line 3: the user 'Dee' is on line 2 too"),
        ("", "the file is empty"),
    ],
)
def test_an_import_with_a_line_not_right_writes_nothing_and_names_it(admin, tmp_path, text, needle) -> None:
    _benchmark(admin)
    assert admin("user", "add", "ann")[0] == 0
    (tmp_path / "people.csv").write_text(text)
    code, out, err = admin("user", "import", str(tmp_path / "people.csv"))
    assert code == 1 and needle in err and out == ""
    assert admin("user", "list")[1].splitlines() == ["ann\tmember\t-"]
