"""The process that owns the chDB directory (`mapservice clickhouse-server`, which `up`
runs) stores the history and answers readiness while long reads hold every statement
handle: inserts and `SELECT 1` have handles of their own."""

from __future__ import annotations

import threading
import time

import pytest

from mapservice.sql.engine import SqlRequest

chdb_engine = pytest.importorskip("mapservice.sql.chdb_engine")

POOL = 2
SLEEP_S = 3


@pytest.fixture
def engine(tmp_path):
    engine = chdb_engine.ChdbEngine(tmp_path / "ch", pool_size=POOL)
    engine.execute(SqlRequest("CREATE TABLE default.t (x UInt32) ENGINE = MergeTree ORDER BY x"))
    yield engine
    engine.close()


def test_inserts_and_ping_do_not_wait_behind_long_statements(engine) -> None:
    readers = [
        threading.Thread(target=engine.execute, args=(SqlRequest(f"SELECT sleep({SLEEP_S})"),))
        for _ in range(POOL)
    ]
    for reader in readers:
        reader.start()
    time.sleep(0.5)  # both statement handles taken
    started = time.monotonic()
    engine.insert("default.t", "TSV", b"1\n2\n", SqlRequest(""))
    assert engine.ping()
    assert engine.execute(SqlRequest("SELECT 1")).body.strip() == b"1"
    took = time.monotonic() - started
    for reader in readers:
        reader.join()
    # Behind the statements they would have waited about SLEEP_S - 0.5 s.
    assert took < 1.5, f"the insert and the pings took {took:.2f} s"
    assert engine.execute(SqlRequest("SELECT count() FROM default.t")).body.strip() == b"2"


def test_inserts_leave_nothing_in_the_system_temporary_directory(tmp_path, monkeypatch) -> None:
    """A process ended by a signal never closes its engine: its insert files' directory is
    beside the data (removed with it), not one more directory left in /tmp per start."""
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    monkeypatch.setattr(chdb_engine.tempfile, "tempdir", str(system_tmp))
    engine = chdb_engine.ChdbEngine(tmp_path / "ch")
    try:
        engine.execute(SqlRequest("CREATE TABLE default.u (x UInt32) ENGINE = Log"))
        engine.insert("default.u", "TSV", b"7\n", SqlRequest(""))
        assert engine.execute(SqlRequest("SELECT sum(x) FROM default.u")).body.strip() == b"7"
        assert list(system_tmp.iterdir()) == []  # checked before close: a kill skips it
        assert list((tmp_path / "ch-inserts").iterdir()) == []
    finally:
        engine.close()
    assert not (tmp_path / "ch-inserts").exists()
