"""Replay reads on a day's partition grown by small inserts: the merge policy against the
engine's default merge selector base (5), interleaved (BENCHMARKS.md, soak).

Two migrated stores in one chDB engine, `policy` and `default` (the policy undone on every
table); each gets HOURS of 20 robots in one part, then INSERTS inserts of 4 poses, 0.1 s
apart; then READS rounds of the store's replay reads, alternating the order. Prints the
active parts of `poses` and each read's median time. From the repository's root:

    PYTHONPATH=. python benchmarks/ingest/2026-11-30-cpu/merge-policy/replay_reads.py 2 600 60
"""

import json
import shutil
import statistics
import sys
import tempfile
import time

from mapservice.adapters.clickhouse.store import ClickHouseStore
from tests.mapservice.adapters.clickhouse.test_merge_policy import ROBOTS, T0_MS, poses_sql

hours, inserts, rounds = (int(a) for a in sys.argv[1:4])
directory = tempfile.mkdtemp(prefix="replay-reads-")
stores = {n: ClickHouseStore(f"chdb://{directory}", database=n) for n in ("policy", "default")}
for name, store in stores.items():
    store.migrate()
    if name == "default":
        for (table,) in store.client.query(
            "SELECT name FROM system.tables WHERE database = 'default' AND engine LIKE '%MergeTree'"
        ).result_rows:
            store.client.command(
                f"ALTER TABLE default.{table} MODIFY SETTING merge_selector_base = 5"
            )
day_rows = hours * 3600 * ROBOTS
for name, store in stores.items():
    store.client.command(poses_sql(name, day_rows, 0))
    store.client.command(f"OPTIMIZE TABLE {name}.poses FINAL")
for i in range(inserts):
    for name, store in stores.items():
        store.client.command(poses_sql(name, 4, day_rows + 4 * i))
    time.sleep(0.1)
time.sleep(2)
end_ms = T0_MS + (day_rows + 4 * inserts) // ROBOTS * 1000
parts = {
    name: store.client.query(
        f"SELECT count() FROM system.parts WHERE database = '{name}' AND table = 'poses' AND active"
    ).result_rows[0][0]
    for name, store in stores.items()
}
reads = {
    "poses, last 10 s": lambda s: s.poses(end_ms - 10_000, end_ms + 1000),
    "poses, last 5 min": lambda s: s.poses(end_ms - 300_000, end_ms + 1000),
    "poses, 10 s an hour back": lambda s: s.poses(end_ms - 3_600_000, end_ms - 3_590_000),
    "robots at the end": lambda s: s.robots_at(end_ms),
    "robots 30 min back": lambda s: s.robots_at(end_ms - 1_800_000),
}
times: dict[tuple[str, str], list[float]] = {(r, n): [] for r in reads for n in stores}
for turn in range(rounds):
    for read_name, read in reads.items():
        order = list(stores.items()) if turn % 2 == 0 else list(stores.items())[::-1]
        for name, store in order:
            started = time.perf_counter()
            assert read(store), (read_name, name)
            times[(read_name, name)].append(time.perf_counter() - started)
medians = {r: {n: round(1000 * statistics.median(times[(r, n)]), 2) for n in stores} for r in reads}
for m in medians.values():
    m["ratio"] = round(m["policy"] / m["default"], 2)
print(json.dumps({"active_parts": parts, "reads_ms": medians}, indent=1))
for store in stores.values():
    store.close()
shutil.rmtree(directory, ignore_errors=True)
