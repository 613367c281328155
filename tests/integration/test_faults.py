"""Fault tests: under a steady QoS 1 load, each part of the service is killed
with SIGKILL and restarted, and ClickHouse refuses inserts for 30 s. Afterwards every
message the MQTT broker acknowledged to its publisher must be in ClickHouse exactly once,
the latest map must equal the fold of the stored chunk history, and every snapshot must
equal the fold of the history at its instant.

Two topologies. The split deployment (Apache Kafka, Mosquitto, `mapservice clickhouse-server`,
`processors`, `api`, `gateway`, each its own process, restarted by the test) lets each part
fail alone and ClickHouse be taken away from a running sink. `mapservice up` (Apache Kafka, the
embedded Mosquitto, `serve`, gateway) is killed piece by piece and its own supervisor
restarts each. Mosquitto runs as the stack runs it for `up`: its store (sessions and queued
QoS 1 messages) in the data dir.

The load (fault_load.py): robots publishing poses and chunks at QoS 1, each message's
identity recorded with whether the broker acknowledged it, counted apart per fault (the
verdict, fault_verdict.py): published, acknowledged, stored, duplicated, lost, and the time
until queryable again. The report is printed and written to test-artifacts/faults.json.

Kafka is the embedded Apache Kafka node (its log on disk): a SIGKILLed broker restarts on
its log, so a Kafka kill, alone or while ClickHouse is down, must lose nothing either.
Where the stacks fall back to tansu (no Java; MAPSERVICE_EMBEDDED_KAFKA=tansu), memory
storage loses what it held at a SIGKILL: messages it had acknowledged to the gateway but
the processors had not yet stored. Those losses are then measured and reported, and what
can be promised is asserted: nothing duplicated, nothing lost that was published after
the new broker was up. docs/delivery.md and docs/embedded.md state the limit.

Each fault runs one second of load before it and keeps its part down one second beyond
its own restart's time; the processors' consumer sessions are 3 s (SHORT_SESSION_ENV), so a
killed processors' partitions go to its restart without the default's 10 s wait.

Bounded: every wait has a timeout and every process is stopped in a finally block; the
module takes about four minutes on the project's 2-core machine shared with other work.
"""

from __future__ import annotations

import os
import signal
import subprocess
import time
from collections.abc import Callable

import pytest

from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.local import embedded
from mapservice.local.stack import Stack
from mapservice.sql.credentials import analyst_password_file
from tests.fixtures.paths import MAPS
from tests.fixtures.up import Up

from .fault_load import (
    CHUNK_EVERY,
    CLICKHOUSE_DOWN_S,
    DOWN_S,
    POSE_PERIOD_S,
    ROBOTS,
    SHORT_SESSION_ENV,
    SNAPSHOT_ENV,
    STEADY_S,
    FaultRun,
    Load,
    Sql,
    run_fault,
)
from .fault_verdict import assert_guarantees, verify, write_report

pytestmark = pytest.mark.long

# ---- the split deployment: the test kills and restarts each part -------------------------

KAFKA_KIND = {"apache": "Apache Kafka (one KRaft node, log on disk)", "tansu": "tansu (memory)"}


def kill(stack: Stack, name: str) -> None:
    """SIGKILL to the component's process group: no clean shutdown, nothing flushed."""
    proc = stack.procs.pop(name)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(30)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    """What `serve` runs, apart (the ClickHouse server, processors, API), as the split
    deployment has it, with the brokers and the gateway."""
    stack = Stack(
        tmp_path_factory.mktemp("faults-split"),
        mqtt="mosquitto",
        apart=True,
        extra_env={**SNAPSHOT_ENV, **SHORT_SESSION_ENV},
    )
    with stack.running(
        stack.start_brokers,
        lambda: stack.publish_meta(meta_for(load_ros_map(MAPS / "depot.yaml"))),
        stack.start_apart,
        stack.start_gateway,
    ):
        yield stack


def split_faults(stack: Stack) -> list[tuple[str, Callable[[], None]]]:
    def restart(name: str) -> None:
        {
            "gateway": stack.start_gateway,
            "api": stack.start_api,
            "mqtt": stack.start_mqtt,
            "kafka": stack.start_kafka,
            "processors": lambda: stack.start_processors(stack.processors_health_port),
            "clickhouse": stack.start_clickhouse_server,
        }[name]()

    def kill_restart(name: str, down_s: float = DOWN_S) -> Callable[[], None]:
        def fault() -> None:
            kill(stack, name)
            time.sleep(down_s)
            restart(name)

        return fault

    def kafka_while_clickhouse_down() -> None:
        # What waited in Kafka for ClickHouse: on disk with Apache Kafka, in tansu's memory only.
        kill(stack, "clickhouse")
        time.sleep(DOWN_S)  # a backlog in Kafka, unstored, when Kafka goes too
        kill(stack, "kafka")
        time.sleep(DOWN_S)
        restart("kafka")
        restart("clickhouse")

    return [
        ("gateway", kill_restart("gateway")),
        ("processors", kill_restart("processors")),
        ("api", kill_restart("api")),
        ("mqtt-broker", kill_restart("mqtt")),
        # The ClickHouse server gone: every insert fails (connection refused) for 30 s.
        ("clickhouse-30s", kill_restart("clickhouse", CLICKHOUSE_DOWN_S)),
        # Last: a new tansu would be a new, empty Kafka (memory storage).
        ("kafka-broker", kill_restart("kafka")),
        ("kafka-while-clickhouse-down", kafka_while_clickhouse_down),
    ]


@pytest.mark.timeout(480)
def test_split_deployment_keeps_every_acknowledged_message_through_each_fault(split) -> None:
    """Split deployment, each part SIGKILLed (ClickHouse down 30 s): acknowledged messages stored once, map and snapshots exact."""
    # Gateway, processors, API, Mosquitto and Kafka SIGKILLed and restarted by the test;
    # losses are allowed only through tansu's memory storage, and are measured.
    started = time.monotonic()
    sql = Sql(
        host="127.0.0.1",
        port=split.clickhouse_port,
        username="default",
        password=split.service_password("clickhouse"),
    )
    load = Load(split.mqtt_url, meta_for(load_ros_map(MAPS / "depot.yaml")))
    runs: list[FaultRun] = []
    try:
        time.sleep(STEADY_S)  # the warmup segment
        for name, fault in split_faults(split):
            runs.append(run_fault(name, load, split.api_url, sql, fault))
            exited = [n for n, p in split.procs.items() if p.poll() is not None]
            assert not exited, f"after the {name} fault, these exited: {exited}"
        load.segment = "after"
        time.sleep(STEADY_S)
        load.stop()
    finally:
        load.close()
    report = {
        "topology": f"split deployment: {KAFKA_KIND[split.kafka]}, Mosquitto (store in the data dir), "
        "clickhouse-server (chDB), processors, api, gateway; restarted by the test",
        "load": {
            "robots": ROBOTS,
            "poses_per_s": ROBOTS / POSE_PERIOD_S,
            "chunks_per_s": ROBOTS / POSE_PERIOD_S / CHUNK_EVERY,
            "qos": 1,
        },
        **verify(sql, split.api_url, load, runs, merge=True),
        "seconds": round(time.monotonic() - started, 1),
    }
    write_report("split", report)
    assert_guarantees(
        report,
        lossy=set() if split.kafka == "apache" else {"kafka-broker", "kafka-while-clickhouse-down"},
    )


# ---- `mapservice up`: its supervisor restarts what the test kills ------------------------


class SupervisedUp(Up):
    """A running `mapservice up` (no simulated robots) on the depot map, restarting a killed
    part after half a second."""

    def __init__(self, data_dir) -> None:
        super().__init__(
            data_dir,
            "--map",
            str(MAPS / "depot.yaml"),
            "--robots",
            "0",
            "--history-days",
            "0",
            "--restart-base-s",
            "0.5",
            env={**os.environ, **SNAPSHOT_ENV, **SHORT_SESSION_ENV, "COLUMNS": "200"},
            ready_within_s=None,
        )

    def children(self) -> dict[str, int]:
        """Component name (as the supervisor says it) -> pid of `up`'s child process."""
        out = subprocess.run(
            ["ps", "-ww", "-o", "pid=,args=", "--ppid", str(self.proc.pid)],
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout
        found = {}
        for line in out.splitlines():
            pid, _, cmd = line.strip().partition(" ")
            if "mapservice.cli gateway" in cmd:
                found["gateway"] = int(pid)
            elif "mapservice.cli processors" in cmd:
                found["processors"] = int(pid)
            elif "mapservice.cli api" in cmd:
                found["api"] = int(pid)
            elif "mapservice.cli clickhouse-server" in cmd:
                found["clickhouse"] = int(pid)
            elif "tansu" in cmd or "kafka.Kafka" in cmd:
                found["kafka"] = int(pid)
            elif "mosquitto" in cmd:
                found["mqtt"] = int(pid)
        return found


@pytest.mark.timeout(600)
def test_up_supervises_each_killed_part_and_keeps_every_acknowledged_message(tmp_path) -> None:
    """`mapservice up` restarts each SIGKILLed part and says so; acknowledged messages stored once, map and snapshots exact."""
    # Gateway, processors, API, ClickHouse server, the embedded Mosquitto and Kafka, one after the other; losses are
    # allowed only through tansu's memory storage (where it is the fallback), and are measured.
    if not embedded.mosquitto_installed():
        pytest.fail("mosquitto is not installed (`make system-deps`)")
    started = time.monotonic()
    up = SupervisedUp(tmp_path / "data")
    load = None
    runs: list[FaultRun] = []
    try:
        up.wait_for("mapservice is up", 150)
        assert "Mosquitto, store in" in up.output  # the embedded default when installed

        def kill_and_wait_restart(name: str) -> Callable[[], None]:
            def fault() -> None:
                mark = len(up.lines)
                children = up.children()
                assert name in children, f"no {name} among up's children: {children}"
                os.killpg(children[name], signal.SIGKILL)
                up.wait_for(f"{name} exited", 20, after=mark)
                up.wait_for(f"{name} restarted", 120, after=mark)

            return fault

        password = analyst_password_file(up.data_dir).read_text().strip()
        sql = Sql(
            host="127.0.0.1",
            port=up.api_port,
            username="analyst",
            password=password,
            proxy_path="/clickhouse",
        )
        load = Load(f"mqtt://127.0.0.1:{up.mqtt_port}", meta_for(load_ros_map(MAPS / "depot.yaml")))
        time.sleep(STEADY_S)  # the warmup segment
        for name in ("gateway", "processors", "api", "clickhouse", "mqtt", "kafka"):
            runs.append(run_fault(f"up-{name}", load, up.api_url, sql, kill_and_wait_restart(name)))
        load.segment = "after"
        time.sleep(STEADY_S)
        load.stop()
        assert "did not start again" not in up.output, up.output[-4000:]
        kafka = "apache" if "Kafka (Apache Kafka" in up.output else "tansu"
        report = {
            "topology": f"mapservice up: {KAFKA_KIND[kafka]}, embedded Mosquitto (store in the "
            "data dir), processors, API and the ClickHouse server over chDB, each "
            "its own process, gateway; restarted "
            "by up's supervisor",
            **verify(sql, up.api_url, load, runs, merge=False),
            "seconds": round(time.monotonic() - started, 1),
        }
    finally:
        if load is not None:
            load.close()
        up.stop()
    write_report("up", report)
    assert_guarantees(report, lossy=set() if kafka == "apache" else {"up-kafka"})
