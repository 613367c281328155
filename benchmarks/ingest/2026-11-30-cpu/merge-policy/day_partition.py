"""Rows merged per insert beside a day's partition, for a merge policy (BENCHMARKS.md, soak).

One chDB process: a `poses`-like table (the columns and codecs of the store's, sorted by
robot) whose day partition holds PREFILL_ROWS (20 robots, a pose a second: 72,000 rows an
hour) in one part, then SECONDS of inserts of 4 poses at 5 a second, as a quiet plant's
processors store them. Prints one JSON line: the process's CPU, the merges and the rows
they read per insert, the partition's active parts.

    python day_partition.py "merge_selector_base=20" 144000 60
"""

import json
import resource
import shutil
import sys
import tempfile
import time

import chdb.session

settings, prefill, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
RATE = 5.0
directory = tempfile.mkdtemp(prefix="day-partition-")
s = chdb.session.Session(directory)
s.query("CREATE DATABASE IF NOT EXISTS m")
s.query(
    "CREATE TABLE m.poses (robot_id LowCardinality(String), "
    "ts DateTime64(3, 'UTC') CODEC(DoubleDelta, ZSTD(3)), x_mm Int32 CODEC(Delta, ZSTD(3)), "
    "y_mm Int32 CODEC(Delta, ZSTD(3)), z_mm Int32 CODEC(Delta, ZSTD(3)), "
    "qx Float32 CODEC(Gorilla, ZSTD(3)), qy Float32 CODEC(Gorilla, ZSTD(3)), "
    "qz Float32 CODEC(Gorilla, ZSTD(3)), qw Float32 CODEC(Gorilla, ZSTD(3)), "
    "battery Nullable(Float32) CODEC(Gorilla, ZSTD(3)), charging LowCardinality(String), "
    "loaded LowCardinality(String), has_path Bool, path_x_mm Array(Int32) CODEC(ZSTD(3)), "
    "path_y_mm Array(Int32) CODEC(ZSTD(3)), recv_lag_ms Int32 CODEC(T64, ZSTD(3))) "
    "ENGINE = ReplacingMergeTree PARTITION BY toDate(ts) ORDER BY (robot_id, ts) "
    "SETTINGS ttl_only_drop_parts = 1" + (f", {settings}" if settings else "")
)
T0 = 1_780_000_000_000 - 1_780_000_000_000 % 86_400_000


def rows_from(n: int, offset_ms: int) -> str:
    second = "intDiv(number, 20)"
    return (
        f"SELECT concat('robot-', toString(number % 20)), "
        f"fromUnixTimestamp64Milli(toInt64({T0} + {offset_ms} + {second} * 1000 + number % 20)), "
        f"toInt32(10000 + 5000 * sin({second} / 60 + number % 20)), "
        f"toInt32(10000 + 5000 * cos({second} / 60 + number % 20)), 0, 0, 0, "
        f"toFloat32(sin({second} / 120)), toFloat32(cos({second} / 120)), "
        f"toFloat32(100 - {second} / 1000 % 80), 'no', 'no', false, [], [], "
        f"toInt32(number % 50) FROM numbers({n})"
    )


def event(name: str) -> int:
    got = s.query(f"SELECT sum(value) FROM system.events WHERE event = '{name}'", "CSV")
    return int(got.data().strip() or 0)


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


if prefill:
    s.query(f"INSERT INTO m.poses {rows_from(prefill, 0)}")
    s.query("OPTIMIZE TABLE m.poses FINAL")
merged0, merges0 = event("MergedRows"), event("Merge")
c0, w0, i = cpu_s(), time.time(), 0
offset = prefill // 20 * 1000
while time.time() - w0 < seconds:
    s.query(f"INSERT INTO m.poses SETTINGS async_insert = 0 {rows_from(4, offset + i * 200)}")
    i += 1
    time.sleep(max(0.0, w0 + i / RATE - time.time()))
c1, w1 = cpu_s(), time.time()
active = s.query(
    "SELECT sum(rows), formatReadableSize(sum(bytes_on_disk)), "
    "formatReadableSize(sum(data_uncompressed_bytes)), count() "
    "FROM system.parts WHERE database = 'm' AND active",
    "CSV",
)
print(
    json.dumps(
        {
            "settings": settings or "default",
            "prefill_h": round(prefill / 20 / 3600, 2),
            "cpu_pct": round(100 * (c1 - c0) / (w1 - w0), 1),
            "inserts": i,
            "merges": event("Merge") - merges0,
            "merged_rows_per_insert": round((event("MergedRows") - merged0) / i),
            "active": active.data().strip(),
        }
    )
)
shutil.rmtree(directory, ignore_errors=True)
