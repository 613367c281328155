"""The platform files in infra/k8s/platform agree with the code: the KafkaUser's ACLs and the
Strimzi topics with the topics and consumer groups the code uses, EMQX's ACL and listeners
with who publishes and subscribes what, the ClickHouse installation, and one Kafka version
across compose, Strimzi and the embedded broker."""

from __future__ import annotations

import re

import yaml

from mapservice.settings import Settings
from tests.fixtures.emqx_acl_eval import emqx_allows, rule_lines
from tests.fixtures.paths import ROOT
from tests.infra.manifests import PLATFORM, k8s_objects


def platform(kind: str) -> dict:
    (doc,) = [d for p, d in k8s_objects() if d["kind"] == kind and p.parent == PLATFORM]
    return doc


def code_consumer_groups() -> set[str]:
    """The consumer group ids the code uses (literal ids and the faust app id's derivatives)."""
    groups = set()
    for path in [
        *ROOT.glob("processors/*.py"),
        *ROOT.glob("ingest/*.py"),
        *ROOT.glob("api/**/*.py"),
        *ROOT.glob("mapservice/adapters/*.py"),
        *ROOT.glob("mapservice/*.py"),
    ]:
        text = path.read_text()
        groups |= set(re.findall(r'"group\.id":\s*"([^"]+)"', text))
        groups |= set(re.findall(r'group_id\s*=\s*"([^"]+)"', text))
        for app_id in re.findall(r'faust\.App\(\s*"([^"]+)"', text):
            groups |= {app_id, f"{app_id}-history"}
    return groups


def acl_allows(acls: list[dict], kind: str, name: str, operation: str) -> bool:
    for acl in acls:
        r = acl["resource"]
        if r["type"] != kind or acl.get("type", "allow") != "allow":
            continue
        matches = (
            name == r["name"]
            if r.get("patternType", "literal") == "literal"
            else name.startswith(r["name"])
        )
        if matches and (operation in acl["operations"] or "All" in acl["operations"]):
            return True
    return False


def test_kafka_user_acls_cover_what_the_code_does() -> None:
    """The KafkaUser may write and read every topic in Settings and read with every consumer group the code uses."""
    acls = platform("KafkaUser")["spec"]["authorization"]["acls"]
    for topic in Settings().kafka_topics:
        for op in ("Read", "Write", "Describe", "Create"):
            assert acl_allows(acls, "topic", topic, op), (topic, op)
    groups = code_consumer_groups()
    assert {
        "mapservice-processors",
        "mapservice-processors-history",
        "mapservice-meta-watcher",
    } <= groups
    for group in groups:
        assert acl_allows(acls, "group", group, "Read"), group
    assert any(
        acl["resource"]["type"] == "cluster" and "IdempotentWrite" in acl["operations"]
        for acl in acls
    )


def test_strimzi_topics_and_kafka_cluster_agree() -> None:
    """The topics name the Kafka cluster the platform file defines, and the bootstrap is its TLS listener."""
    kafka = platform("Kafka")
    name = kafka["metadata"]["name"]
    topics = [d for p, d in k8s_objects() if d["kind"] == "KafkaTopic"]
    assert topics and all(t["metadata"]["labels"]["strimzi.io/cluster"] == name for t in topics)
    config = next(
        d
        for _, d in k8s_objects()
        if d["kind"] == "ConfigMap" and d["metadata"]["name"] == "mapservice"
    )["data"]
    (tls,) = [lst for lst in kafka["spec"]["kafka"]["listeners"] if lst["tls"]]
    assert config["MAPSERVICE_KAFKA_BOOTSTRAP"] == f"{name}-kafka-bootstrap.kafka.svc:{tls['port']}"
    assert config["MAPSERVICE_KAFKA_SECURITY_PROTOCOL"] == "SASL_SSL"
    assert tls["authentication"]["type"] == config["MAPSERVICE_KAFKA_SASL_MECHANISM"].lower()


def emqx_config() -> str:
    return platform("EMQX")["spec"]["config"]["data"]


def acl_rules() -> list[str]:
    cm = next(d for p, d in k8s_objects() if d["kind"] == "ConfigMap" and p.parent == PLATFORM)
    return rule_lines(cm["data"]["acl.conf"])


def test_emqx_acl_lets_each_party_do_only_its_part() -> None:
    """Gateway subscribes through its share group, processors publish advertisements, a robot
    publishes its own pose and chunks only (not another's, not the 2019 chunk topic, not as a
    wildcard username) and reads advertisements; the rest is denied."""
    s = Settings(mqtt_share_group="mapservice")
    rules = acl_rules()
    for topic in s.mqtt_subscriptions:
        assert emqx_allows(rules, "mapservice-gateway", "subscribe", topic), topic
    assert emqx_allows(rules, "mapservice-processors", "publish", s.advertisement_topic)
    coordinates, chunks = (
        s.coordinate_topic.removesuffix("#"),
        s.robot_chunk_topic.removesuffix("+"),
    )
    for robot in ("r1", "agv-7.hall_2@plant:1"):
        assert emqx_allows(rules, robot, "publish", f"{coordinates}{robot}")
        assert emqx_allows(rules, robot, "publish", f"{chunks}{robot}")
        assert emqx_allows(rules, robot, "subscribe", s.advertisement_topic)
        assert not emqx_allows(rules, robot, "publish", f"{coordinates}someone-else")
        assert not emqx_allows(rules, robot, "publish", f"{chunks}someone-else")
        assert not emqx_allows(rules, robot, "publish", s.create_chunk_topic)  # 2019 topic: closed
        for spy in ("#", s.coordinate_topic, f"{chunks}+", f"$share/x/{s.coordinate_topic}"):
            assert not emqx_allows(rules, robot, "subscribe", spy), spy
        assert not emqx_allows(rules, robot, "publish", s.advertisement_topic)
    # A VDA 5050 vehicle (username <manufacturer>/<serialNumber>) publishes in its own
    # subtree only, and reads its own orders and instant actions.
    for sub in ("state", "visualization", "connection", "factsheet"):
        assert emqx_allows(rules, "Acme/001", "publish", f"uagv/v2/Acme/001/{sub}")
        assert not emqx_allows(rules, "Acme/001", "publish", f"uagv/v2/Acme/002/{sub}")
    assert not emqx_allows(rules, "Acme/001", "publish", "uagv/v2/Acme/001/order")
    assert emqx_allows(rules, "Acme/001", "subscribe", "uagv/v2/Acme/001/order")
    assert emqx_allows(rules, "Acme/001", "subscribe", "uagv/v2/Acme/001/instantActions")
    assert not emqx_allows(rules, "Acme/001", "subscribe", "uagv/v2/Acme/002/order")
    assert not emqx_allows(rules, "Acme/001", "subscribe", "uagv/#")
    for bad in ("Acme/+", "#/1", "a/b/c"):
        assert not emqx_allows(rules, bad, "publish", "uagv/v2/Acme/001/state"), bad
    # A master control orders every vehicle and reads their messages, and nothing else.
    master = "mapservice-master-plant"
    for serial in ("001", "002"):
        for sub in ("order", "instantActions"):
            assert emqx_allows(rules, master, "publish", f"uagv/v2/Acme/{serial}/{sub}")
        assert not emqx_allows(rules, master, "publish", f"uagv/v2/Acme/{serial}/state")
    for sub in ("state", "visualization", "connection", "factsheet"):
        assert emqx_allows(rules, master, "subscribe", f"uagv/+/+/+/{sub}")
    assert not emqx_allows(rules, master, "subscribe", "uagv/#")
    assert not emqx_allows(rules, master, "subscribe", "uagv/+/+/+/order")
    assert not emqx_allows(rules, master, "publish", f"{coordinates}{master}")
    assert not emqx_allows(rules, "mapservice-master-a/b", "publish", "uagv/v2/Acme/001/order")
    # A username with wildcards or slashes renders no topic filter it could abuse.
    for bad in ("#", "+", "a/b"):
        assert not emqx_allows(rules, bad, "publish", f"{coordinates}someone-else")
    assert not emqx_allows(rules, "mapservice-gateway", "subscribe", "#")
    assert rules[-1] == "{deny, all}."
    assert "no_match = deny" in emqx_config()
    assert re.search(r"password_based[^}]*backend = built_in_database", emqx_config(), re.S)


def test_emqx_acl_lets_only_the_robot_read_its_commands() -> None:
    """A robot reads its own command topic and answers on its own command-events topic;
    another robot can neither read those commands (not even by a wildcard) nor answer
    them; the gateway delivers every robot's commands and reads every robot's answers."""
    s = Settings(mqtt_share_group="mapservice")
    rules = acl_rules()
    assert emqx_allows(rules, "mapservice-gateway", "publish", s.command_topic("r1"))
    assert emqx_allows(
        rules, "mapservice-gateway", "subscribe", f"$share/mapservice/{s.command_response_filter}"
    )
    for robot, other in (("r1", "r2"), ("agv-7.hall_2@plant:1", "r1")):
        assert emqx_allows(rules, robot, "subscribe", s.command_topic(robot))
        assert emqx_allows(rules, robot, "publish", f"iot/robots/{robot}/command-events")
        assert not emqx_allows(rules, robot, "subscribe", s.command_topic(other))
        assert not emqx_allows(rules, robot, "publish", f"iot/robots/{other}/command-events")
        assert not emqx_allows(
            rules, robot, "publish", s.command_topic(robot)
        )  # no forged commands
        for spy in ("iot/robots/+/commands", "iot/robots/#", f"$share/x/{s.command_topic(other)}"):
            assert not emqx_allows(rules, robot, "subscribe", spy), spy
    for bad in ("+", "#", "a/b"):
        assert not emqx_allows(rules, bad, "subscribe", s.command_topic("r1")), bad


def test_emqx_acl_lets_the_gateway_send_vda_vehicles_instant_actions_only() -> None:
    """Operators' commands reach a VDA 5050 vehicle as instantActions from the gateway; the
    gateway sends no orders and a vehicle cannot send itself instant actions."""
    rules = acl_rules()
    assert emqx_allows(rules, "mapservice-gateway", "publish", "uagv/v2/acme/agv-1/instantActions")
    assert not emqx_allows(rules, "mapservice-gateway", "publish", "uagv/v2/acme/agv-1/order")
    assert not emqx_allows(rules, "acme/agv-1", "publish", "uagv/v2/acme/agv-1/instantActions")


def test_no_robot_can_take_another_clients_session_on_emqx() -> None:
    """Robots' listeners force client id = username (no gateway or robot session takeover); the internal zone of the gateways does not."""
    config = emqx_config()
    top = re.search(r"^mqtt \{(.*?)^\}", config, re.S | re.M)
    assert top and re.search(r"use_username_as_clientid = true", top[1])
    internal = re.search(r"^zones\.internal \{(.*?)^\}", config, re.S | re.M)
    assert internal and "use_username_as_clientid = false" in internal[1]
    for name in ("tcp.default", "ssl.default"):
        listener = re.search(rf"^listeners\.{re.escape(name)} \{{(.*?)^\}}", config, re.S | re.M)
        assert listener and "zone" not in listener[1], name  # the default zone: forced ids
    internal_listener = re.search(r"^listeners\.tcp\.internal \{(.*?)^\}", config, re.S | re.M)
    assert internal_listener and "zone = internal" in internal_listener[1]


def test_emqx_has_a_tls_listener_for_robots() -> None:
    """EMQX opens a TLS listener (8883) with a certificate from a mounted Secret."""
    config = emqx_config()
    listener = re.search(r"listeners\.ssl\.default \{(.*?)\n\}", config, re.S)
    assert listener and 'bind = "0.0.0.0:8883"' in listener.group(1)
    certfile = re.search(r'certfile = "([^"]+)"', listener.group(1)).group(1)
    spec = platform("EMQX")["spec"]["coreTemplate"]["spec"]
    mounts = {m["name"]: m["mountPath"] for m in spec["extraVolumeMounts"]}
    volumes = {v["name"]: v for v in spec["extraVolumes"]}
    (name,) = [n for n, path in mounts.items() if certfile.startswith(path + "/")]
    assert "secret" in volumes[name]


def test_emqx_internal_zone_holds_a_gateway_restart_at_plant_load() -> None:
    """The gateways' zone queues at least 60 s of one gateway's share of 10,000 robots, and keeps sessions for hours."""
    config = emqx_config()
    zone = config[config.index("zones.internal") :]
    queue = int(re.search(r"max_mqueue_len = (\d+)", zone).group(1))
    inflight = int(re.search(r"max_inflight = (\d+)", zone).group(1))
    expiry_h = int(re.search(r"session_expiry_interval = (\d+)h", zone).group(1))
    gateways, robots, events_per_robot_s = (
        4,
        10_000,
        1.2,
    )  # BENCHMARKS.md: 1,000 robots -> 1,200 events/s
    assert queue >= robots * events_per_robot_s / gateways * 60
    assert inflight >= 1000 and expiry_h >= 1
    assert re.search(r"listeners\.tcp\.internal \{[^}]*zone = internal", config)
    config_map = next(
        d
        for _, d in k8s_objects()
        if d["kind"] == "ConfigMap" and d["metadata"]["name"] == "mapservice"
    )
    port = int(
        re.search(r'listeners\.tcp\.internal \{\s*bind = "0\.0\.0\.0:(\d+)"', config).group(1)
    )
    assert config_map["data"]["MAPSERVICE_MQTT_URL"].endswith(f":{port}")


def test_clickhouse_installation_is_replicated_with_keeper_and_a_readonly_analyst() -> None:
    """Two replicas, a Keeper ensemble it points at, and an analyst user whose profile is read-only with limits."""
    chi, chk = platform("ClickHouseInstallation"), platform("ClickHouseKeeperInstallation")
    (cluster,) = chi["spec"]["configuration"]["clusters"]
    assert cluster["layout"]["replicasCount"] >= 2
    assert chk["spec"]["configuration"]["clusters"][0]["layout"]["replicasCount"] == 3
    keeper_host = chi["spec"]["configuration"]["zookeeper"]["nodes"][0]["host"]
    assert keeper_host.startswith(chk["metadata"]["name"])
    users, profiles = (
        chi["spec"]["configuration"]["users"],
        chi["spec"]["configuration"]["profiles"],
    )
    profile = users["mapservice_analyst/profile"]
    assert profiles[f"{profile}/readonly"] == "1"
    for name in ("readonly", "max_execution_time", "max_result_rows", "max_memory_usage"):
        assert f"{profile}/constraints/{name}/const" in profiles, name
    assert (
        int(profiles[f"{profile}/max_execution_time"]) > 0
        and int(profiles[f"{profile}/max_result_rows"]) > 0
    )
    assert "mapservice_analyst/quota" in users
    # The engine's own access control: SELECT on the service's database and on the system
    # tables the parser allows, no source grant (FILE, URL, REMOTE, ...).
    from mapservice.sql.allow_list import ALLOWED_SYSTEM_TABLES

    assert sorted(users["mapservice_analyst/grants/query"]) == sorted(
        ["GRANT SELECT ON mapservice.*"]
        + [f"GRANT SELECT ON system.{t}" for t in ALLOWED_SYSTEM_TABLES]
    )
    assert not any(k.startswith("mapservice_analyst/allow_databases") for k in users)
    settings = chi["spec"]["configuration"]["settings"]
    assert settings["user_files_path"].rstrip("/").endswith("user_files_none")
    (no_hosts,) = chi["spec"]["configuration"]["files"].values()
    assert "<remote_url_allow_hosts></remote_url_allow_hosts>" in no_hosts
    config = next(
        d
        for _, d in k8s_objects()
        if d["kind"] == "ConfigMap" and d["metadata"]["name"] == "mapservice"
    )["data"]
    assert config["MAPSERVICE_CLICKHOUSE_USERNAME"] in {u.split("/")[0] for u in users}
    assert (
        f"clickhouse-{chi['metadata']['name']}.clickhouse.svc"
        in config["MAPSERVICE_CLICKHOUSE_DSN"]
    )


def test_compose_strimzi_and_the_embedded_broker_run_one_kafka_version() -> None:
    """The pom the embedded broker's jars come from, the compose image and the Strimzi
    Kafka name the same Apache Kafka version."""
    from mapservice.local.kafka_broker import kafka_version

    compose = yaml.safe_load((ROOT / "infra" / "compose.yaml").read_text())
    image = compose["services"]["kafka"]["image"]
    assert image == f"apache/kafka:{kafka_version()}"
    assert str(platform("Kafka")["spec"]["kafka"]["version"]) == kafka_version()


def test_emqx_refuses_robots_every_shared_subscription_of_the_service() -> None:
    """No robot, vehicle or master control subscribes to `$share/<group>/<filter>` for any
    topic robots deal with (wildcards included) nor publishes there: the ACL refuses it as
    sent, and since EMQX 5 authorizes `$share/<group>/t` as `t` (a master control may read
    every vehicle's state, so the ACL alone would let it join the gateways' group there),
    the robots' listeners have no shared subscriptions at all; the gateways' zone has."""
    s = Settings(mqtt_share_group="mapservice")
    rules = acl_rules()
    for topic in s.mqtt_subscriptions:
        assert emqx_allows(rules, "mapservice-gateway", "subscribe", topic), topic
    gateway_filters = [f.removeprefix("$share/mapservice/") for f in s.mqtt_subscriptions]
    tried = 0
    for identity in ("r1", "agv-7.hall_2@plant:1", "Acme/001", "mapservice-master-plant"):
        filters = [
            *gateway_filters,
            s.advertisement_topic,
            s.zone_advertisement_topic,
            f"{s.coordinate_topic.removesuffix('#')}{identity}",
            "#",
            "+",
            "iot/#",
            f"{s.vda5050_interface}/#",
        ]
        for group in ("mapservice", "g", "robots"):
            for topic_filter in filters:
                shared = f"$share/{group}/{topic_filter}"
                assert not emqx_allows(rules, identity, "subscribe", shared), (identity, shared)
                assert not emqx_allows(rules, identity, "publish", shared), (identity, shared)
                tried += 1
    assert tried >= 4 * 3 * 15
    config = emqx_config()
    top = re.search(r"^mqtt \{(.*?)^\}", config, re.S | re.M)
    assert top and re.search(r"^\s*shared_subscription = false$", top[1], re.M)
    internal = re.search(r"^zones\.internal \{(.*?)^\}", config, re.S | re.M)
    assert internal and re.search(r"^\s*shared_subscription = true$", internal[1], re.M)
    for name in ("tcp.default", "ssl.default"):
        listener = re.search(rf"^listeners\.{re.escape(name)} \{{(.*?)^\}}", config, re.S | re.M)
        assert listener and "zone" not in listener[1], name  # robots: the default zone
