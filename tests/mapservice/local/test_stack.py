"""The local stack's gateway replicas: their client ids, shared subscription and ports; the
fetch wait its components get on each embedded Kafka."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapservice.local.private_dir import protect_data_dir
from mapservice.local.stack import Stack
from mapservice.settings import Settings


@pytest.fixture(autouse=True)
def _no_mqtt_identity_in_env(monkeypatch):
    for name in ("MAPSERVICE_MQTT_CLIENT_ID", "MAPSERVICE_MQTT_SHARE_GROUP"):
        monkeypatch.delenv(name, raising=False)


def test_one_gateway_keeps_the_default_client_id_and_subscribes_alone(tmp_path):
    """A single gateway: no replica client id, no shared subscription, one health port."""
    stack = Stack(tmp_path, mqtt="mosquitto")
    env = stack.env("gateway")
    assert "MAPSERVICE_MQTT_CLIENT_ID" not in env and "MAPSERVICE_MQTT_SHARE_GROUP" not in env
    assert stack.gateway_health_ports == [stack.health_port]


def test_gateway_replicas_share_the_subscription_each_with_its_own_session_and_port(tmp_path):
    """Two replicas: client ids -1 and -2 (two persistent sessions), one share group, two
    health ports; other components get neither."""
    stack = Stack(tmp_path, mqtt="mosquitto", gateways=2)
    first, second = stack.env("gateway"), stack.env("gateway-2")
    assert first["MAPSERVICE_MQTT_CLIENT_ID"] == "mapservice-gateway-1"
    assert second["MAPSERVICE_MQTT_CLIENT_ID"] == "mapservice-gateway-2"
    assert (
        first["MAPSERVICE_MQTT_SHARE_GROUP"]
        == second["MAPSERVICE_MQTT_SHARE_GROUP"]
        == "mapservice-gateways"
    )
    assert "MAPSERVICE_MQTT_SHARE_GROUP" not in stack.env("server")
    assert (
        len(set(stack.gateway_health_ports)) == 2
        and stack.gateway_health_ports[0] == stack.health_port
    )


def test_replicas_keep_a_configured_client_id_base_and_share_group(tmp_path):
    """MAPSERVICE_MQTT_CLIENT_ID and MAPSERVICE_MQTT_SHARE_GROUP, when set, are the base and
    the group."""
    stack = Stack(
        tmp_path,
        mqtt="mosquitto",
        gateways=2,
        extra_env={"MAPSERVICE_MQTT_CLIENT_ID": "plant-gw", "MAPSERVICE_MQTT_SHARE_GROUP": "plant"},
    )
    env = stack.env("gateway-2")
    assert (env["MAPSERVICE_MQTT_CLIENT_ID"], env["MAPSERVICE_MQTT_SHARE_GROUP"]) == (
        "plant-gw-2",
        "plant",
    )


def test_no_gateway_is_refused(tmp_path):
    """gateways=0 is an error naming the value."""
    with pytest.raises(ValueError, match="at least 1"):
        Stack(tmp_path, mqtt="mosquitto", gateways=0)


def test_a_chosen_port_taken_before_its_server_starts_is_chosen_again(tmp_path):
    """The ClickHouse server's and the processors' health ports are chosen when the stack is
    made and bound seconds later; a client connection may take one meanwhile (a restarted
    `up` failed so). Chosen ports taken by then are chosen again, before anyone is told
    them; a given port is kept (and refused by the start, naming it)."""
    import socket

    stack = Stack(tmp_path, mqtt="mosquitto", apart=True)
    taken = stack.clickhouse_port
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", taken))
        holder.listen()
        stack._rechoose_if_taken("clickhouse_port", "the ClickHouse server")
        assert stack.clickhouse_port != taken
        assert f"127.0.0.1:{stack.clickhouse_port}" in stack.env("api")["MAPSERVICE_CLICKHOUSE_DSN"]
        # Told to a component now: a later start keeps it whatever happens.
        chosen = stack.clickhouse_port
        stack._rechoose_if_taken("clickhouse_port", "the ClickHouse server")
        assert stack.clickhouse_port == chosen

        given = Stack(tmp_path, mqtt="mosquitto", apart=True, clickhouse_port=taken)
        given._rechoose_if_taken("clickhouse_port", "the ClickHouse server")
        assert given.clickhouse_port == taken


def test_a_chosen_gateway_health_port_taken_before_the_gateway_starts_is_chosen_again(tmp_path):
    """Each gateway replica's health port is chosen with the stack and bound only after
    Kafka, the MQTT broker and the history have started; another process may take it
    meanwhile, and `up` then stopped on "port ... for the gateway's health endpoint is
    already in use". Replica 1's is `health_port`, which `up` prints; a given one is kept."""
    import socket

    stack = Stack(tmp_path, mqtt="mosquitto", gateways=2)
    first, second = stack.gateway_health_ports
    with socket.socket() as a, socket.socket() as b:
        for holder, port in ((a, first), (b, second)):
            holder.bind(("127.0.0.1", port))
            holder.listen()
        stack._rechoose_if_taken("gateway-1", "the gateway's health endpoint")
        stack._rechoose_if_taken("gateway-2", "the gateway-2's health endpoint")
        assert first not in stack.gateway_health_ports and second not in stack.gateway_health_ports
        assert stack.health_port == stack.gateway_health_ports[0]

        given = Stack(tmp_path, mqtt="mosquitto", health_port=first)
        given._rechoose_if_taken("gateway-1", "the gateway's health endpoint")
        assert given.health_port == first == given.gateway_health_ports[0]


def test_publishing_the_map_meta_releases_its_producer(tmp_path, monkeypatch):
    """The stack's meta publisher is closed once the meta is on Kafka, and when it could not
    be: else its producer goes on dialling the broker until the process ends."""
    from mapservice.adapters.ros_map import load_ros_map, meta_for
    from mapservice.testing.memory_publisher import MemoryPublisher
    from tests.fixtures.paths import MAPS

    made: list[MemoryPublisher] = []
    fail: list[Exception] = []

    def publisher(settings, client_id):
        made.append(MemoryPublisher(fail_with=fail[0] if fail else None))
        return made[-1]

    monkeypatch.setattr("mapservice.local.stack.KafkaPublisher", publisher)
    stack = Stack(tmp_path, mqtt="mosquitto")
    meta = meta_for(load_ros_map(MAPS / "depot.yaml"))
    stack.publish_meta(meta)
    assert made[-1].closed and made[-1].records
    fail.append(OSError("broker gone"))
    with pytest.raises(RuntimeError, match="could not publish the map meta"):
        stack.publish_meta(meta)
    assert made[-1].closed


def test_protecting_the_data_dir_passes_over_a_file_that_vanishes_meanwhile(
    tmp_path, monkeypatch
) -> None:
    """A running engine's scratch file listed by the walk and deleted before its mode is
    read: skipped, and the rest still made private."""
    data = tmp_path / "data"
    (data / "clickhouse").mkdir(parents=True)
    gone = data / "clickhouse" / "scratch"
    gone.write_text("x")
    kept = data / "kept.txt"
    kept.write_text("x")
    kept.chmod(0o644)
    real_lstat = Path.lstat

    def lstat(self, *args, **kwargs):
        if self == gone:
            raise FileNotFoundError(2, "No such file or directory", str(self))
        return real_lstat(self, *args, **kwargs)

    monkeypatch.setattr(Path, "lstat", lstat)
    protect_data_dir(data)
    assert kept.stat().st_mode & 0o077 == 0


def test_stop_ends_replicas_with_their_kind_before_the_brokers(tmp_path, monkeypatch):
    """Whatever order the components were started in, `stop` ends the clients before the
    brokers they need for a clean shutdown: a replica ("processors-2", "gateway-3",
    "api-2") with its kind, so never after Kafka; a name of no kind comes last."""
    import random

    from mapservice.local.lifetime import STOP_ORDER

    kinds = [k for k in STOP_ORDER if k != "guard"]
    rng = random.Random(5)
    for _ in range(30):
        names = [k for k in kinds if rng.random() < 0.7]
        names += [f"{k}-{n}" for k in ("gateway", "api", "processors") for n in (1, 2, 3)]
        names += ["elsewhere"]
        rng.shuffle(names)
        stopped: list[str] = []
        stack = Stack(tmp_path / "data", mqtt="mosquitto")
        stack.procs = {name: name for name in names}  # type: ignore[misc]
        monkeypatch.setattr(
            "mapservice.local.stack.embedded.stop",
            lambda proc, stopped=stopped: proc is None or stopped.append(proc),  # None: none
        )
        stack.stop()
        assert sorted(stopped) == sorted(names) and not stack.procs
        rank = [
            kinds.index(n if n in kinds else n.rsplit("-", 1)[0])
            if n != "elsewhere"
            else len(kinds)
            for n in stopped
        ]
        assert rank == sorted(rank), stopped


@pytest.mark.parametrize("component", ["server", "processors", "api", "gateway", None])
def test_components_on_tansu_fetch_with_a_short_wait_and_on_apache_kafka_with_the_default(
    tmp_path, monkeypatch, component
):
    """tansu answers a fetch only when its wait runs out, so every component of a stack on
    it waits 50 ms; on Apache Kafka (which answers on arrival) they keep the settings'
    default of 500 ms, and a wait the operator set is kept on either."""
    monkeypatch.delenv("MAPSERVICE_KAFKA_FETCH_WAIT_MS", raising=False)
    on_tansu = Stack(tmp_path / "t", mqtt="mosquitto", kafka="tansu")
    on_apache = Stack(tmp_path / "a", mqtt="mosquitto", kafka="apache")
    assert on_tansu.env(component)["MAPSERVICE_KAFKA_FETCH_WAIT_MS"] == "50"
    assert "MAPSERVICE_KAFKA_FETCH_WAIT_MS" not in on_apache.env(component)
    assert (on_tansu.settings().kafka_fetch_wait_ms, on_apache.settings().kafka_fetch_wait_ms) == (
        50,
        Settings().kafka_fetch_wait_ms,
    )
    assert Settings().kafka_fetch_wait_ms == 500
    monkeypatch.setenv("MAPSERVICE_KAFKA_FETCH_WAIT_MS", "120")
    assert on_tansu.env(component)["MAPSERVICE_KAFKA_FETCH_WAIT_MS"] == "120"


@pytest.mark.parametrize("component", ["server", "processors", "api", "gateway", None])
def test_the_embedded_apache_kafka_gets_one_partition_a_topic_unless_told(
    tmp_path, monkeypatch, component
):
    """One processors replica reads the embedded Apache Kafka: its topics are made with one
    partition (the broker's CPU follows produce requests, one per partition); tansu and a
    Kafka of the operator's keep the settings' default, and a count the operator set is kept."""
    monkeypatch.delenv("MAPSERVICE_KAFKA_PARTITIONS", raising=False)
    on_apache = Stack(tmp_path / "a", mqtt="mosquitto", kafka="apache")
    on_tansu = Stack(tmp_path / "t", mqtt="mosquitto", kafka="tansu")
    external = Stack(tmp_path / "e", mqtt="mosquitto", kafka="127.0.0.1:9")
    assert on_apache.env(component)["MAPSERVICE_KAFKA_PARTITIONS"] == "1"
    assert on_apache.settings().kafka_partitions == 1
    for other in (on_tansu, external):
        assert "MAPSERVICE_KAFKA_PARTITIONS" not in other.env(component)
        assert other.settings().kafka_partitions == Settings().kafka_partitions == 6
    chosen = Stack(
        tmp_path / "c",
        mqtt="mosquitto",
        kafka="apache",
        extra_env={"MAPSERVICE_KAFKA_PARTITIONS": "3"},
    )
    assert chosen.env(component)["MAPSERVICE_KAFKA_PARTITIONS"] == "3"
    assert chosen.settings().kafka_partitions == 3
    monkeypatch.setenv("MAPSERVICE_KAFKA_PARTITIONS", "4")
    assert on_apache.env(component)["MAPSERVICE_KAFKA_PARTITIONS"] == "4"
    assert on_apache.settings().kafka_partitions == 4
