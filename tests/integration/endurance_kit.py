"""The endurance test's (test_retention_endurance.py) robots, operator and clock: a simulated
clock the stack's processes share, a QoS 1 publisher that remembers what was acknowledged
(the writes, poses and conflicts the checks fold by brute force), an operator annotating
through the API who remembers each edit (and folds them), and the analyst's view of the
history's size."""

from __future__ import annotations

import threading
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

RATE = 17_280  # a simulated day every 5 real seconds


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


def history_bytes(stack: Stack) -> int | None:
    """Bytes of the history's active parts, as an analyst reads them through the API
    (None while the API is away, e.g. restarting, or slow: the drive loop tries again on
    its next turn, where a long wait would cost simulated days)."""
    password = analyst_password_file(stack.data_dir).read_text().strip()
    sql = (
        f"SELECT sum(total_bytes) FROM system.tables "
        f"WHERE database = '{stack.settings().clickhouse_database}'"
    )
    try:
        r = httpx.post(
            f"{stack.api_url}/clickhouse/",
            content=sql.encode(),
            auth=("analyst", password),
            timeout=3,
        )
    except httpx.HTTPError:
        return None
    return int(r.text.strip()) if r.status_code == 200 else None


class Drive:
    """Publishes at QoS 1 and remembers what was acknowledged."""

    def __init__(self, stack: Stack) -> None:
        host, port, _ = parse_mqtt_url(stack.mqtt_url)
        self.client = make_client(f"endurance-{time.time_ns()}", clean_session=False)
        # Back within a second of the broker's restart: paho's default back-off doubles up
        # to two minutes, and each real second of it is hours of the simulated clock.
        self.client.reconnect_delay_set(min_delay=0.2, max_delay=1)
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


class Restart:
    """Restarts one of the stack's components on a thread of its own, so the drive loop
    goes on meanwhile: a restart takes real seconds, which are simulated days on the
    clock."""

    def __init__(self, stack: Stack, component: str, drive: Drive) -> None:
        self.component = component
        self.error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._run, args=(stack, drive), name=f"restart-{component}", daemon=True
        )
        self._thread.start()

    def _run(self, stack: Stack, drive: Drive) -> None:
        try:
            stack.restart(self.component)
            if self.component == "mqtt":  # the robots' client reconnects, then publishes again
                drive.wait_connected()
        except BaseException as exc:  # noqa: BLE001 - raised again on the test's thread
            self.error = exc

    def finished(self, timeout_s: float = 0) -> bool:
        """Whether the restart is over (waiting up to `timeout_s`); raises what it raised."""
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            return False
        if self.error is not None:
            raise RuntimeError(f"restarting {self.component} failed") from self.error
        return True


class Operator:
    """Annotates the floor through the API as the admin (an operator may edit), remembering
    each edit at the instant the API gave it."""

    def __init__(self, stack: Stack) -> None:
        self.url = f"{stack.api_url}/api/v1/annotations"
        self.headers = {"Authorization": f"Bearer {stack.api_secrets().admin}"}
        self.edits: list[tuple[int, str, str, dict | None]] = []  # ts, id, change, annotation

    def stands(self, annotation_id: str, timeout_s: float = 60) -> None:
        """Waits until the API lists `annotation_id` (an edit is stored through Kafka and
        the processors: seconds of real time, which are simulated hours here)."""
        deadline = time.monotonic() + timeout_s
        while True:
            r = httpx.get(self.url, headers=self.headers, timeout=30)
            if r.status_code == 200 and any(
                a["id"] == annotation_id for a in r.json()["annotations"]
            ):
                return
            assert time.monotonic() < deadline, f"{annotation_id} not stored: {r.text[:300]}"
            time.sleep(0.2)

    def edit(self, change: str, annotation_id: str, body: dict | None, clock: SimClock) -> None:
        if change != "create":  # the operator edits what the API shows
            self.stands(annotation_id)
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
