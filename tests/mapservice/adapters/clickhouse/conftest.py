"""Fixtures of the store-contract modules here: one chDB engine per module and an empty,
migrated store of each kind (memory and chDB). A module with fixtures of its own name
(`chdb_dir`, `store`) overrides these."""

from __future__ import annotations

import itertools

import pytest

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.testing.memory_store import MemoryStore

_databases = itertools.count()


@pytest.fixture(scope="module")
def chdb_dir(tmp_path_factory):
    """One chDB engine for the module, closed at its end so other modules may open theirs."""
    path = tmp_path_factory.mktemp("chdb") / "ch"
    root = ClickHouseStore(f"chdb://{path}", database="contract_root")
    root.migrate()
    yield path
    root.close()


@pytest.fixture(params=["memory", "clickhouse"])
def store(request):
    """An empty, migrated store of each kind."""
    if request.param == "memory":
        s = MemoryStore()
    else:
        path = request.getfixturevalue("chdb_dir")
        s = ClickHouseStore(f"chdb://{path}", database=f"contract_{next(_databases)}")
    s.migrate()
    yield s
    s.close()
