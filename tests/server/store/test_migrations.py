"""The schema's versions: the base revision is this release's tables, an older database is refused until it is
upgraded (``kitti-eval admin db upgrade``, or at start when told to), a database the previous release wrote
keeps every record and board after the upgrade, and a newer one is refused. SQLite here; PostgreSQL too when
its binaries are installed (a throwaway cluster)."""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from server_helpers import app_client
from server_postgres import PostgresCluster, why_no_postgres
from sqlalchemy import create_engine, text

from kitti_eval.cli import main
from kitti_eval_server.errors import StartupRefused
from kitti_eval_server.store import Store
from kitti_eval_server.store.database import metadata
from kitti_eval_server.store.schema import head

PREVIOUS = Path(__file__).resolve().parent / "previous_release"
NO_PG = why_no_postgres()


def _schema_differences(url: str) -> list[Any]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return compare_metadata(MigrationContext.configure(conn), metadata)
    finally:
        engine.dispose()


def test_a_new_database_is_made_at_the_newest_revision_with_the_tables_of_the_code(tmp_path: Path) -> None:
    """database.py's tables are what the revisions make: a change to one without a migration fails here."""
    url = f"sqlite:///{tmp_path / 'new.db'}"
    store = Store(url)
    assert store.create_schema(upgrade=False) is None  # empty: made, whatever ``upgrade`` says
    assert store.schema_state().revision == head()
    store.dispose()
    assert _schema_differences(url) == []


def _previous_sqlite(data_dir: Path) -> Path:
    data_dir.mkdir(parents=True)
    with gzip.open(PREVIOUS / "sqlite.db.gz", "rb") as f, open(data_dir / "kitti-eval.db", "wb") as out:
        shutil.copyfileobj(f, out)
    return data_dir


def _expected(backend: str) -> dict[str, Any]:
    return json.loads((PREVIOUS / f"{backend}.expected.json").read_text())


def _holds(now: Any, before: Any, where: str) -> None:
    """``now`` says everything ``before`` said: the same values, lists of the same length in the same order; a
    field a later release added to an object (a team on a submission) is allowed, none missing or changed."""
    if isinstance(before, dict):
        assert isinstance(now, dict), where
        for key, value in before.items():
            assert key in now, f"{where}.{key} is gone"
            _holds(now[key], value, f"{where}.{key}")
    elif isinstance(before, list):
        assert isinstance(now, list) and len(now) == len(before), where
        for i, (a, b) in enumerate(zip(now, before, strict=True)):
            _holds(a, b, f"{where}[{i}]")
    else:
        assert now == before, f"{where}: {now!r} != {before!r}"


def _answers_as_before(c: Any, expected: dict[str, Any]) -> None:
    tokens = expected["tokens"]
    assert expected["asked"], "the fixture asked nothing"
    for asked, before in expected["asked"].items():
        who, path = asked.split(" ", 1)
        headers = {} if who == "anyone" else {"Authorization": f"Bearer {tokens.get(who, expected['admin'])}"}
        r = c.get(path, headers=headers)
        assert r.status_code == 200, (asked, r.text)
        _holds(r.json(), before, asked)


def _settings(expected: dict[str, Any], **more: Any) -> dict[str, Any]:
    return {"auth": "accounts", "register_demo": False, "warmup": False, "admin_token": expected["admin"], **more}


def _refused_until_upgraded(data_dir: Path, expected: dict[str, Any], where: list[str], **db: Any) -> None:
    with pytest.raises(StartupRefused) as refused, app_client(data_dir, **_settings(expected, **db)):
        pass
    message = refused.value.message
    assert "made by a release before the schema had versions" in message, message
    assert "kitti-eval admin db upgrade" in message and "KITTI_EVAL_DB_UPGRADE=true" in message
    assert main(["admin", *where, "db", "current"]) == 0
    assert main(["admin", *where, "db", "upgrade"]) == 0
    assert main(["admin", *where, "db", "upgrade"]) == 0  # again: nothing to do
    with app_client(data_dir, **_settings(expected, **db)) as c:
        _answers_as_before(c, expected)


def test_the_previous_release_s_sqlite_database_upgrades_and_keeps_every_record(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data_dir = _previous_sqlite(tmp_path / "data")
    expected = _expected("sqlite")
    _refused_until_upgraded(data_dir, expected, ["--data-dir", str(data_dir)])
    err = capsys.readouterr().err
    assert "is unversioned (made by a release before the schema had versions" in err
    assert f"upgraded the database {data_dir / 'kitti-eval.db'} from no revision to revision {head()}" in err
    assert "already at revision" in err
    assert _schema_differences(f"sqlite:///{data_dir / 'kitti-eval.db'}") == []


def test_told_to_the_service_upgrades_at_start(tmp_path: Path) -> None:
    data_dir = _previous_sqlite(tmp_path / "data")
    expected = _expected("sqlite")
    with app_client(data_dir, **_settings(expected, db_upgrade=True)) as c:
        _answers_as_before(c, expected)
        assert c.app.state.service.store.schema_state().revision == head()


def test_a_database_a_newer_release_upgraded_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data_dir = tmp_path / "data"
    with app_client(data_dir, warmup=False, register_demo=False):
        pass
    engine = create_engine(f"sqlite:///{data_dir / 'kitti-eval.db'}")
    with engine.begin() as conn:
        conn.execute(text("UPDATE alembic_version SET version_num = 'ffff0002'"))
    engine.dispose()
    for upgrade in (False, True):
        with pytest.raises(StartupRefused) as refused, app_client(data_dir, warmup=False, db_upgrade=upgrade):
            pass
        assert "at revision ffff0002, which this release does not know (a newer release upgraded it)" in (
            refused.value.message
        )
    assert main(["admin", "--data-dir", str(data_dir), "db", "upgrade"]) == 1
    assert "run the release that upgraded it, or a newer one" in capsys.readouterr().err


@pytest.fixture(scope="module")
def postgres() -> Any:
    if NO_PG:
        pytest.skip(NO_PG)
    with PostgresCluster() as cluster:
        yield cluster


def test_on_postgresql_the_base_revision_is_the_code_s_tables(postgres: Any) -> None:
    url = postgres.url.rpartition("/")[0] + "/fresh"
    engine = create_engine(postgres.url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.execute(text("CREATE DATABASE fresh"))
    engine.dispose()
    store = Store(url.replace("postgresql://", "postgresql+psycopg://"))
    store.create_schema(upgrade=False)
    store.dispose()
    assert _schema_differences(url.replace("postgresql://", "postgresql+psycopg://")) == []


def test_the_previous_release_s_postgresql_database_upgrades_and_keeps_every_record(
    postgres: Any, tmp_path: Path
) -> None:
    import psycopg

    with psycopg.connect(host="127.0.0.1", port=postgres.port, user="postgres", autocommit=True) as conn:
        conn.execute("CREATE DATABASE previous")
    with psycopg.connect(host="127.0.0.1", port=postgres.port, user="postgres", dbname="previous") as conn:
        dump = gzip.decompress((PREVIOUS / "postgresql.sql.gz").read_bytes()).decode()
        # pg_dump's plain SQL, but for psql's own meta-commands (\restrict, \unrestrict), which are not SQL
        conn.execute("\n".join(line for line in dump.splitlines() if not line.startswith("\\")))  # type: ignore[arg-type]
    url = postgres.url.rpartition("/")[0] + "/previous"
    expected = _expected("postgresql")
    _refused_until_upgraded(tmp_path / "data", expected, ["--database-url", url], database_url=url)
