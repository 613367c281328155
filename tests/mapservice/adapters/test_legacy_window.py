"""The newest-first 2019 listing first looks for its rows in the hour before "now": the
service's clock's now (a simulated clock's, when settings ask for one), not the wall's."""

from __future__ import annotations

from mapservice.adapters.clickhouse.store import ClickHouseStore
from mapservice.core.legacy_query import ChunkQuery
from mapservice.settings import Settings

SIMULATED_NOW = 1_700_000_000_000  # long before the wall clock


def test_the_first_window_ends_at_the_service_clock_s_now() -> None:
    store = ClickHouseStore.from_settings(
        Settings(
            clock_start=str(SIMULATED_NOW), clock_rate=1e-9, clickhouse_dsn="http://127.0.0.1:1"
        )
    )
    lowers: list[int] = []

    def run(sql: str, params: dict) -> list:
        if "lower" in params:
            lowers.append(params["lower"])
        return [()] * 10  # a full page: the first window answers

    store._legacy_rows("SELECT 1 FROM t", ChunkQuery(limit=10), run)
    assert len(lowers) == 1
    assert abs(lowers[0] - (SIMULATED_NOW - 3_600_000)) < 1000
