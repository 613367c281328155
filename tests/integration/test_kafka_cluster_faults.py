"""A Kafka broker lost under load: three KRaft nodes on 127.0.0.1 (each broker and
controller, as the Strimzi `dual-role` pool runs them), topics with replication factor 3
and `min.insync.replicas` 2, the gateway's idempotent producer with `acks=all`, robots
publishing at QoS 1 through Mosquitto. First the leader of a pose partition is SIGKILLed
and started again once the others have fenced it and elected new leaders, then the active
controller (the quorum's leader, from the nodes' quorum-state files), the same way. Every message the MQTT broker acknowledged must be stored exactly
once; the report (the fault table of test_faults.py, section `kafka-cluster` of
test-artifacts/faults.json) says how long each took to recover.

Bounded: every wait has a timeout, every process is stopped in a finally block; about a
minute and a half and ~1 GB of memory (three JVMs of 256 MB heap) on the project's machine.
"""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from confluent_kafka.admin import AdminClient

from mapservice.adapters.ros_map import load_ros_map, meta_for
from mapservice.local import embedded, kafka_broker
from mapservice.local.stack import Stack
from mapservice.sql.credentials import analyst_password_file
from tests.fixtures.paths import MAPS

from .conftest import wait_for_meta
from .fault_load import (
    DOWN_S,
    ROBOTS,
    SNAPSHOT_ENV,
    STEADY_S,
    Load,
    Sql,
    now_ms,
    queryable,
    run_fault,
)
from .fault_verdict import verify, write_report

pytestmark = pytest.mark.long

NODES = (1, 2, 3)


class Cluster:
    """Three KRaft nodes, each its own process group, log dir and ports (fixed, so a
    restarted node finds its voters where they were)."""

    def __init__(self, root: Path) -> None:
        ports = {i: (embedded.free_port(), embedded.free_port()) for i in NODES}
        voters = ",".join(f"{i}@127.0.0.1:{ports[i][1]}" for i in NODES)
        self.configs = {
            i: kafka_broker.KafkaNodeConfig(
                log_dir=root / f"node-{i}" / "log",
                port=ports[i][0],
                controller_port=ports[i][1],
                node_id=i,
                voters=voters,
                replication=3,
                min_insync_replicas=2,
            )
            for i in NODES
        }
        self.cluster_id = kafka_broker.cluster_id()
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self.procs: dict = {}
        self._admin: AdminClient | None = None

    @property
    def bootstrap(self) -> str:
        return ",".join(f"127.0.0.1:{c.port}" for c in self.configs.values())

    def start(self, node: int) -> None:
        log = open(self.root / f"node-{node}.log", "ab")
        self.procs[node] = kafka_broker.launch(self.configs[node], log, cluster=self.cluster_id)

    def start_all(self) -> None:
        # Side by side: each node's first start formats its log (a JVM of its own) first.
        with ThreadPoolExecutor(len(NODES)) as pool:
            list(pool.map(self.start, NODES))
        self.wait_complete()

    def kill(self, node: int) -> None:
        proc = self.procs.pop(node)
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(30)

    def restart(self, node: int) -> None:
        self.start(node)
        self.wait_complete()

    def stop(self) -> None:
        self._admin = None  # AdminClient has no close: its last reference gone, it ends
        for proc in self.procs.values():
            kafka_broker.stop_process_group(proc)
        self.procs.clear()

    def admin(self) -> AdminClient:
        """One client for every poll (each new one dials all three nodes anew)."""
        if self._admin is None:
            self._admin = AdminClient({"bootstrap.servers": self.bootstrap, "log_level": 0})
        return self._admin

    def wait_complete(self, timeout_s: float = 90) -> None:
        """Until all three brokers are in the metadata and every partition has all three
        replicas in sync again (so the next fault starts from a whole cluster)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for node, proc in self.procs.items():
                assert proc.poll() is None, f"Kafka node {node} exited ({proc.returncode})"
            try:
                md = self.admin().list_topics(timeout=5)
                if len(md.brokers) == len(NODES) and all(
                    len(p.isrs) == len(NODES)
                    for t in md.topics.values()
                    for p in t.partitions.values()
                ):
                    return
            except Exception:  # noqa: BLE001 - a node still starting
                pass
            time.sleep(0.5)
        raise AssertionError(f"the Kafka cluster was not whole again within {timeout_s:.0f} s")

    def wait_failed_over(self, node: int, timeout_s: float = 60) -> None:
        """Until the cluster has taken over from a killed node: the controller fenced it (it
        is gone from the metadata), no partition is led by it, and the quorum's leader is
        another node; so the restart comes after real elections, not before them."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                md = self.admin().list_topics(timeout=5)
                if (
                    node not in md.brokers
                    and self.active_controller() != node
                    and all(
                        p.leader != node for t in md.topics.values() for p in t.partitions.values()
                    )
                ):
                    return
            except Exception:  # noqa: BLE001 - between elections
                pass
            time.sleep(0.2)
        raise AssertionError(f"the cluster did not take over from node {node} in {timeout_s:.0f} s")

    def partition_leader(self, topic: str, partition: int = 0) -> int:
        return (
            self.admin().list_topics(topic, timeout=10).topics[topic].partitions[partition].leader
        )

    def active_controller(self) -> int:
        """The KRaft quorum's leader, as the running nodes last wrote it down."""
        states = []
        for node in self.procs:
            path = self.configs[node].log_dir / "__cluster_metadata-0" / "quorum-state"
            state = json.loads(path.read_text())
            states.append((state["leaderEpoch"], state["leaderId"]))
        epoch, leader = max(states)
        assert leader in NODES, f"no quorum leader (epoch {epoch})"
        return leader


@pytest.mark.timeout(420)
def test_a_lost_broker_and_a_lost_controller_lose_and_duplicate_nothing(tmp_path) -> None:
    """Three KRaft nodes (RF 3, min ISR 2, acks=all): the partition leader, then the active controller SIGKILLed and restarted; every acknowledged message stored once."""
    if kafka_broker.java_binary() is None:
        pytest.fail("no Java runtime for Apache Kafka (`make system-deps` installs it)")
    started = time.monotonic()
    cluster = Cluster(tmp_path / "kafka")
    meta = meta_for(load_ros_map(MAPS / "depot.yaml"))
    stack = Stack(
        tmp_path / "stack",
        mqtt="mosquitto",
        kafka=cluster.bootstrap,
        extra_env={"MAPSERVICE_KAFKA_REPLICATION": "3", **SNAPSHOT_ENV},
    )
    load = None
    killed: dict[str, dict] = {}
    try:
        cluster.start_all()
        stack.start(
            stack.start_brokers,
            lambda: stack.publish_meta(meta),
            stack.start_server,
            stack.start_gateway,
            lambda: wait_for_meta(stack),
        )
        cluster.wait_complete()
        password = analyst_password_file(stack.data_dir).read_text().strip()
        sql = Sql(
            host="127.0.0.1",
            port=stack.api_port,
            username="analyst",
            password=password,
            proxy_path="/clickhouse",
        )
        load = Load(stack.mqtt_url, meta)
        time.sleep(STEADY_S)  # the warmup segment
        pose_topic = stack.settings().topic_pose_events

        def kill_restart(which: Callable[[], int]) -> Callable[[], None]:
            def fault() -> None:
                node = which()
                t0, killed_ms = time.monotonic(), now_ms()
                cluster.kill(node)
                cluster.wait_failed_over(node)
                failed_over = time.monotonic() - t0
                # The service stores again on the two nodes left (min.insync.replicas 2).
                deadline = time.monotonic() + 60
                while not queryable(stack.api_url, f"{fault.__name__}-0", killed_ms + 1):
                    assert time.monotonic() < deadline, "nothing stored on the two nodes left"
                    time.sleep(0.2)
                serving = time.monotonic() - t0
                time.sleep(DOWN_S)
                cluster.restart(node)
                killed[fault.__name__] = {
                    "node": node,
                    "failed_over_s": round(failed_over, 2),
                    "stored_without_it_s": round(serving, 2),
                    "back_in_sync_s": round(time.monotonic() - t0, 2),
                }

            return fault

        faults = [
            ("partition-leader", lambda: cluster.partition_leader(pose_topic)),
            ("active-controller", cluster.active_controller),
        ]
        runs = []
        for name, which in faults:
            fault = kill_restart(which)
            fault.__name__ = name
            runs.append(run_fault(name, load, stack.api_url, sql, fault))
            exited = [n for n, p in stack.procs.items() if p.poll() is not None]
            assert not exited, f"after the {name} fault, these exited: {exited}"
        load.segment = "after"
        time.sleep(STEADY_S)
        load.stop()
        report = {
            "topology": "mapservice serve + gateway + Mosquitto on three Apache Kafka KRaft "
            "nodes (broker and controller each; replication factor 3, "
            "min.insync.replicas 2, acks=all); nodes restarted by the test",
            # Per fault: the node killed, when the others had fenced it and re-elected
            # its partitions' leaders and the quorum's, when a message published after
            # the kill was queryable (the node still down), and when it was back with
            # every partition fully in sync.
            "killed_nodes": killed,
            "load": {"robots": ROBOTS, "qos": 1},
            **verify(sql, stack.api_url, load, runs, merge=False),
            "seconds": round(time.monotonic() - started, 1),
        }
    finally:
        if load is not None:
            load.close()
        stack.stop()
        cluster.stop()
    write_report("kafka-cluster", report)
    print(json.dumps(killed))
    for r in report["faults"]:
        assert r["acknowledged"] > 0.9 * r["published"], r
        assert r["lost"] == 0 and r["duplicated"] == 0 and r["wrong_content"] == 0, r
        if r["fault"] not in ("warmup", "after"):
            assert r["recovery_s"] is not None and r["caught_up_s"] is not None, r
    assert report["checks"]["latest_map_equals_fold"], report["checks"]
    assert not report["checks"]["wrong_snapshots"], report["checks"]
