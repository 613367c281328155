"""An insert the embedded engine fails on a disk too full to hold it is refused as a server
refuses it, NOT_ENOUGH_SPACE (code 243), whichever file the engine failed on: the history's
readiness reason then names the cause and its hint ("free disk space ..."). Any other
failure keeps its own code, and a disk's low space alone fails nothing."""

from __future__ import annotations

import shutil
from collections import namedtuple

import pytest

from mapservice.runtime.insert_health import InsertHealth
from mapservice.sql.engine import SqlError, SqlRequest

chdb_engine = pytest.importorskip("mapservice.sql.chdb_engine")

Usage = namedtuple("Usage", "total used free")
ROWS = b"".join(b"%d\n" % i for i in range(1000))


@pytest.fixture(scope="module")
def engine(tmp_path_factory):
    engine = chdb_engine.ChdbEngine(tmp_path_factory.mktemp("disk") / "ch")
    engine.execute(SqlRequest("CREATE TABLE default.t (x UInt32) ENGINE = MergeTree ORDER BY x"))
    yield engine
    engine.close()


def free_bytes(monkeypatch, free: int) -> None:
    real = shutil.disk_usage

    def usage(path):
        return Usage(real(path).total, real(path).total - free, free)

    monkeypatch.setattr(chdb_engine.shutil, "disk_usage", usage)


# Failures of every kind the engine reports (a wrong table, rows that do not parse, a
# format it does not know), each on a disk with room and on one without.
FAILING = [
    ("default.missing", "TSV", ROWS),
    ("default.t", "TSV", b"not a number\n"),
    ("default.t", "NoSuchFormat", ROWS),
]


@pytest.mark.parametrize("target,fmt,rows", FAILING)
@pytest.mark.parametrize("short_of_room", [None, 1000, 1])
def test_a_failed_insert_on_a_full_disk_is_not_enough_space(
    engine, monkeypatch, target, fmt, rows, short_of_room
) -> None:
    """No byte free, or fewer than twice the rows and a MiB (by 1000 bytes, by one)."""
    free = 0 if short_of_room is None else 2 * len(rows) + (1 << 20) - short_of_room
    free_bytes(monkeypatch, free)
    with pytest.raises(SqlError) as refused:
        engine.insert(target, fmt, rows, SqlRequest(""))
    assert refused.value.code == 243
    health = InsertHealth()
    health.failed(refused.value)
    assert health.last_error_code == "NOT_ENOUGH_SPACE"
    reason = health.reason()
    assert reason is not None and "free disk space" in reason and f"{free} bytes free" in reason


@pytest.mark.parametrize("target,fmt,rows", FAILING)
def test_a_failed_insert_with_room_on_the_disk_keeps_its_own_error(
    engine, monkeypatch, target, fmt, rows
) -> None:
    free_bytes(monkeypatch, 2 * len(rows) + (1 << 20))
    with pytest.raises(SqlError) as refused:
        engine.insert(target, fmt, rows, SqlRequest(""))
    assert refused.value.code != 243 and "NOT_ENOUGH_SPACE" not in str(refused.value)


def test_an_insert_that_succeeds_on_a_nearly_full_disk_succeeds(engine, monkeypatch) -> None:
    free_bytes(monkeypatch, 0)
    before = int(engine.execute(SqlRequest("SELECT count() FROM default.t")).body)
    engine.insert("default.t", "TSV", ROWS, SqlRequest(""))
    assert int(engine.execute(SqlRequest("SELECT count() FROM default.t")).body) == before + 1000
