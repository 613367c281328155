"""Helpers of the store contract modules (test_store_*_contract.py): a chDB store in the
module's engine and incompressible pixels. Their fixtures (`store`, `chdb_dir`, `t0`) are
in tests/conftest.py."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from mapservice.adapters.clickhouse.store import ClickHouseStore

_databases = itertools.count()


def clickhouse_store(chdb_dir: Path) -> ClickHouseStore:
    """A new, unmigrated ClickHouseStore: a database of its own in the module's chDB."""
    return ClickHouseStore(f"chdb://{chdb_dir}", database=f"contract_{next(_databases)}")


def random_pixels(seed: int, n: int = 100 * 100) -> bytes:
    # Incompressible pixels make zlib bytes that are not valid UTF-8.
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()
