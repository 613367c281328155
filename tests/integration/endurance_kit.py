"""The endurance test's (test_retention_endurance.py) robots, operator and clock: a simulated
clock the stack's processes share, a QoS 1 publisher that remembers what was acknowledged
(the writes, poses and conflicts the checks fold by brute force), the scenes it drives for
the incident rules, an operator annotating through the API who remembers each edit (and
folds them), and the analyst's view of the history's size."""

from __future__ import annotations

import time

import httpx

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
from mapservice.core.event_incidents import CLOCK_GROWN_KINDS, grows_with_the_clock
from mapservice.core.incident_model import Incident, IncidentThresholds
from mapservice.core.ports import PoseRow
from mapservice.core.wire2019 import (
    content_hash,
    encode_chunk_create,
    encode_coordinates,
    format_timestamp,
)
from mapservice.local.stack import Stack
from mapservice.sql.credentials import analyst_password_file

# A simulated day every 10 real seconds. The retention (seven days) is then 70 real seconds,
# and that is how far the history may fall behind what the robots had acknowledged before
# the sink drops an event as older than the retention (the product's rule) while the checks'
# brute-force fold still counts it. A Kafka broker's restart takes 20-40 s under load, and
# after a restart the snapshot timer catches up the days it cost in one run that holds the
# store thread the sink shares (10-32 s measured at twice this rate): at twice this rate
# (35 s) runs failed that way under a load average of 12-27.
RATE = 8640


class SimClock:
    def __init__(self, start_ms: int, origin_ms: int, rate: float = RATE) -> None:
        self.start_ms, self.origin_ms, self.rate = start_ms, origin_ms, rate

    def now_ms(self) -> int:
        return self.start_ms + int((time.time_ns() // 1_000_000 - self.origin_ms) * self.rate)

    def env(self) -> dict[str, str]:
        return {
            "MAPSERVICE_CLOCK_START": str(self.start_ms),
            "MAPSERVICE_CLOCK_ORIGIN": str(self.origin_ms),
            "MAPSERVICE_CLOCK_RATE": str(self.rate),
        }


class Write:
    def __init__(self, row, column, ts_ms, robot_id, pixels) -> None:
        self.row, self.column, self.ts_ms, self.robot_id = row, column, ts_ms, robot_id
        self.pixels, self.content_hash = pixels, content_hash(pixels).hex()


def incident_fields(incident: Incident | dict) -> tuple:
    """What the endurance test compares of an incident, as the rules found it or as
    GET /api/v1/incidents lists it: everything but the id (the key), and but the end and
    length of one that grows with the clock (the finder's clock, compared apart)."""
    if isinstance(incident, dict):
        i = incident
        evidence = tuple((e["robotId"], e["ts_ms"], e["x"], e["y"]) for e in i["evidence"])
        grows = i["ongoing"] and i["kind"] in CLOCK_GROWN_KINDS
        end, measure = (None, None) if grows else (i["end_ms"], i["measure"])
        return (
            i["kind"],
            tuple(i["robots"]),
            i["start_ms"],
            end,
            i["ongoing"],
            i["x"],
            i["y"],
            i["severity"],
            measure,
            evidence,
        )
    grows = grows_with_the_clock(incident)
    return (
        incident.kind,
        incident.robots,
        incident.start_ms,
        None if grows else incident.end_ms,
        incident.ongoing,
        incident.x,
        incident.y,
        incident.severity,
        None if grows else incident.measure,
        tuple((e.robot_id, e.ts_ms, e.x, e.y) for e in incident.evidence),
    )


def kafka_keeps_records(stack: Stack) -> bool:
    """Whether a restart of the stack's Kafka broker keeps the topics' records: a stack
    that says so (`kafka_keeps_records`, or `kafka` naming its broker: Apache Kafka keeps
    its log in the data dir), else every broker but tansu's in-memory one."""
    said = getattr(stack, "kafka_keeps_records", None)
    if said is not None:
        return bool(said)
    broker = getattr(stack, "kafka", None)
    if broker in ("apache", "tansu"):
        return broker == "apache"
    proc = stack.procs.get("kafka")
    return proc is not None and "tansu" not in " ".join(map(str, proc.args))


def analyst_number(stack: Stack, sql: str) -> int | None:
    """One number an analyst reads through the API's /clickhouse (None while the API is
    away, e.g. restarting, or the answer is empty). `{db}` in `sql` names the service's
    database."""
    password = analyst_password_file(stack.data_dir).read_text().strip()
    try:
        r = httpx.post(
            f"{stack.api_url}/clickhouse/",
            content=sql.format(db=stack.settings().clickhouse_database).encode(),
            auth=("analyst", password),
            timeout=10,
        )
    except httpx.HTTPError:
        return None
    text = r.text.strip()
    return int(text) if r.status_code == 200 and text.lstrip("-").isdigit() else None


def bytes_by_table(stack: Stack) -> dict[str, int]:
    """The history's active bytes per table, as an analyst reads them through the API's
    /clickhouse (analyst SQL on system.tables; empty while the API is away, e.g.
    restarting): their sum is the flat-storage check's figure."""
    password = analyst_password_file(stack.data_dir).read_text().strip()
    database = stack.settings().clickhouse_database
    sql = (
        f"SELECT name, total_bytes FROM system.tables WHERE database = '{database}' "
        "AND total_bytes > 0 ORDER BY total_bytes DESC FORMAT TSV"
    )
    try:
        r = httpx.post(
            f"{stack.api_url}/clickhouse/",
            content=sql.encode(),
            auth=("analyst", password),
            timeout=10,
        )
    except httpx.HTTPError:
        return {}
    if r.status_code != 200:
        return {}
    return {name: int(n) for name, n in (line.split("\t") for line in r.text.splitlines())}


# Each day-partitioned history table the retention drops, with the SQL of its oldest
# instant (epoch ms).
OLDEST_SQL = {
    "chunk_events": "toUnixTimestamp64Milli(min(ts))",
    "zone_violations": "toUnixTimestamp64Milli(min(ts))",
    "incidents": "toUnixTimestamp64Milli(min(start))",
    "heatmap_cells": "toUnixTimestamp(min(bucket)) * 1000",
}


def oldest_history_ms(stack: Stack) -> int | None:
    """The oldest row of the history's day-partitioned tables (OLDEST_SQL; the earliest of
    them, ms), as an analyst reads them; None while unknown."""
    oldest = []
    for table, sql in OLDEST_SQL.items():
        ms = analyst_number(stack, f"SELECT {sql} FROM {{db}}.{table}")
        if ms is None:
            return None
        oldest.append(ms)
    return min(oldest)


class Drive:
    """Publishes at QoS 1 and remembers what was acknowledged."""

    def __init__(self, stack: Stack) -> None:
        host, port, _ = parse_mqtt_url(stack.mqtt_url)
        self.client = make_client(f"endurance-{time.time_ns()}", clean_session=False)
        self.client.connect(host, port)
        self.client.loop_start()
        self.pending: list = []
        self.written: list[Write] = []
        self.poses: list[tuple[str, int]] = []
        self.pose_rows: list[PoseRow] = []  # the same poses as the store keeps them
        self.conflicts: set[tuple] = set()

    def publish(self, topic: str, payload: bytes) -> None:
        self.pending.append(self.client.publish(topic, payload, qos=1))

    def chunk(self, row: int, column: int, ts: int, robot: str, pixels: bytes) -> Write:
        w = Write(row, column, ts, robot, pixels)
        self.written.append(w)
        self.publish(
            "iot/chunks/create",
            encode_chunk_create(row, column, pixels, format_timestamp(ts), robot),
        )
        return w

    def pose(
        self,
        robot: str,
        ts: int,
        x: float,
        y: float = 2.0,
        battery: float = 50.0,
        path: tuple[tuple[float, float], ...] | None = None,
    ) -> None:
        # whole millimetres, as the store keeps positions: the rules' brute force reads
        # what the processors read
        x, y = round(x * 1000) / 1000, round(y * 1000) / 1000
        self.poses.append((robot, ts))
        self.pose_rows.append(
            PoseRow(robot, ts, x, y, 0.0, 0.0, 0.0, 0.0, 1.0, battery, False, None, path, ts)
        )
        self.publish(
            f"iot/coordinates/{robot}",
            encode_coordinates(
                robot,
                format_timestamp(ts),
                x,
                y,
                battery_level=battery,
                path=None if path is None else list(path),
            ),
        )

    def scene(self, still: str, passing: str, start_ms: int, th: IncidentThresholds) -> int:
        """Two robots report densely (every half offline threshold) for a stuck window and
        more, 4 m from the others' lane: `still` stands with a path ahead (stuck), `passing`
        drives by it at twice the moving speed, half the near-miss distance beside it (a
        near miss), its last pose's battery just below the low level (battery_low). Both
        fall silent after it (offline, as between any two of the drive's poses). Returns
        the scene's last instant."""
        every = th.offline_after_ms // 2
        n = th.stuck_ms // every + 3
        span_m = 2 * th.moving_m_s * (n - 1) * every / 1000
        x0, y0 = 5.0, 6.0
        for k in range(n):
            ts = start_ms + k * every
            self.pose(still, ts, x0, y0, path=((x0 + 1.0, y0), (x0 + 2.0, y0)))
            low = k == n - 1
            battery = th.battery_low_percent - 1 if low else 50.0
            x = x0 - span_m / 2 + span_m * k / (n - 1)
            self.pose(passing, ts, x, y0 + th.near_miss_m / 2, battery=battery)
        return start_ms + (n - 1) * every

    def acknowledged(self) -> None:
        for info in self.pending:
            info.wait_for_publish(60)
            assert info.is_published(), "a QoS 1 publish was not acknowledged"
        self.pending.clear()

    def wait_connected(self, timeout_s: float = 60) -> None:
        deadline = time.monotonic() + timeout_s
        while not self.client.is_connected():
            assert time.monotonic() < deadline, "the robots' client never reconnected"
            time.sleep(0.1)

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


class Operator:
    """Annotates the floor through the API as the admin (an operator may edit), remembering
    each edit at the instant the API gave it."""

    def __init__(self, stack: Stack) -> None:
        self.url = f"{stack.api_url}/api/v1/annotations"
        self.headers = {"Authorization": f"Bearer {stack.api_secrets().admin}"}
        self.edits: list[tuple[int, str, str, dict | None]] = []  # ts, id, change, annotation

    def edit(self, change: str, annotation_id: str, body: dict | None, clock: SimClock) -> None:
        if change == "create":
            r = httpx.post(
                self.url,
                json={**(body or {}), "id": annotation_id},
                headers=self.headers,
                timeout=30,
            )
        elif change == "change":
            r = httpx.put(
                f"{self.url}/{annotation_id}", json=body, headers=self.headers, timeout=30
            )
        else:
            r = httpx.delete(f"{self.url}/{annotation_id}", headers=self.headers, timeout=30)
        assert r.status_code in (200, 201, 204), (
            f"{change} {annotation_id}: {r.status_code} {r.text}"
        )
        if change == "remove":
            # No body: the removal's instant is at most now. Every instant checked is days
            # later, where that is the same fold.
            self.edits.append((clock.now_ms(), annotation_id, change, None))
        else:
            doc = r.json()
            self.edits.append((doc["changed_ms"], annotation_id, change, doc["annotation"]))

    def standing_at(self, t: int) -> dict[str, tuple[dict | None, int, int]]:
        """The brute-force fold: each annotation standing at t, with when it was created
        and last changed."""
        current: dict[str, tuple[dict | None, int, int]] = {}
        for ts, annotation_id, change, doc in sorted(self.edits, key=lambda e: e[0]):
            if ts > t:
                break
            if change == "create":
                current[annotation_id] = (doc, ts, ts)
            elif change == "change":
                current[annotation_id] = (doc, current[annotation_id][1], ts)
            else:
                del current[annotation_id]
        return current
