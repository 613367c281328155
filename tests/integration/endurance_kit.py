"""The endurance test's (test_retention_endurance.py) robots, operator and clock: a simulated
clock the stack's processes share, a QoS 1 publisher that remembers what was acknowledged
(the writes, poses and conflicts the checks fold by brute force), an operator annotating
through the API who remembers each edit (and folds them), and the analyst's view of the
history's size."""

from __future__ import annotations

import time

import httpx

from mapservice.adapters.mqtt_client import make_client, parse_mqtt_url
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


def history_bytes(stack: Stack) -> int | None:
    """Bytes of the history's active parts, as an analyst reads them through the API
    (None while the API is away, e.g. restarting)."""
    return analyst_number(
        stack, "SELECT sum(total_bytes) FROM system.tables WHERE database = '{db}'"
    )


def oldest_history_ms(stack: Stack) -> int | None:
    """The oldest chunk write and zone violation the history holds (the earlier of the two,
    ms), as an analyst reads them; None while unknown."""
    oldest = []
    for table in ("chunk_events", "zone_violations"):
        ms = analyst_number(stack, f"SELECT toUnixTimestamp64Milli(min(ts)) FROM {{db}}.{table}")
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

    def pose(self, robot: str, ts: int, x: float) -> None:
        self.poses.append((robot, ts))
        self.publish(
            f"iot/coordinates/{robot}",
            encode_coordinates(robot, format_timestamp(ts), x, 2.0, battery_level=50.0),
        )

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
