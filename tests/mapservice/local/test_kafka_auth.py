"""The embedded Apache Kafka's credentials under `--auth` (local/kafka_auth.py): the node's
listeners, what every component is told, and tansu's refusal. The broker itself refusing a
producer without them: tests/integration/test_kafka_auth.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from mapservice.local import kafka_broker
from mapservice.local.kafka_auth import KAFKA_NODE_USER, KAFKA_SERVICE_USER, listener_properties
from mapservice.local.stack import Stack


def properties(users) -> dict[str, str]:
    node = kafka_broker.KafkaNodeConfig(Path("/tmp/log"), 9092, 9093, sasl_users=users)
    return dict(line.split("=", 1) for line in node.properties().splitlines() if "=" in line)


def test_with_users_no_listener_takes_a_client_without_sasl() -> None:
    users = (("node", "n" * 32), ("svc", "s" * 32))
    props = properties(users)
    protocols = dict(p.split(":") for p in props["listener.security.protocol.map"].split(","))
    listeners = [item.split("://")[0] for item in props["listeners"].split(",")]
    assert {protocols[name] for name in listeners} == {"SASL_PLAINTEXT"}
    assert props["sasl.enabled.mechanisms"] == "PLAIN"
    clients = props["listener.name.sasl_plaintext.plain.sasl.jaas.config"]
    controller = props["listener.name.controller.plain.sasl.jaas.config"]
    assert f'user_svc="{"s" * 32}"' in clients and f'user_node="{"n" * 32}"' in clients
    assert "user_svc" not in controller  # only the node itself talks to its controller
    plain = properties(())
    assert plain["listeners"].startswith("PLAINTEXT://") and "sasl.enabled.mechanisms" not in plain


@pytest.mark.parametrize("name, password", [("svc", 'a"b'), ("svc", "a b;"), ('x" y', "p" * 8)])
def test_a_name_or_password_that_would_break_the_jaas_line_is_refused(name, password) -> None:
    with pytest.raises(ValueError, match="A-Z a-z 0-9"):
        listener_properties(1, 2, (("node", "n" * 32), (name, password)))


def test_every_component_gets_the_services_kafka_user(tmp_path) -> None:
    stack = Stack(tmp_path, mqtt="mosquitto", mqtt_auth=True, kafka="apache", kafka_auth=True)
    users = dict(stack.kafka_users())
    assert set(users) == {KAFKA_NODE_USER, KAFKA_SERVICE_USER}
    assert users[KAFKA_NODE_USER] != users[KAFKA_SERVICE_USER]
    for component in ("gateway", "gateway-2", "server", "processors", "api", None):
        env = stack.env(component)
        assert env["MAPSERVICE_KAFKA_SECURITY_PROTOCOL"] == "SASL_PLAINTEXT"
        assert env["MAPSERVICE_KAFKA_USERNAME"] == KAFKA_SERVICE_USER
        assert env["MAPSERVICE_KAFKA_PASSWORD"] == users[KAFKA_SERVICE_USER]
    conf = stack.settings().kafka_config()
    assert conf["sasl.username"] == KAFKA_SERVICE_USER and conf["sasl.mechanism"] == "PLAIN"
    secret = tmp_path / "secrets" / f"kafka-{KAFKA_SERVICE_USER}-password"
    assert secret.stat().st_mode & 0o077 == 0
    without = Stack(tmp_path / "open", mqtt="mosquitto", kafka="apache")
    # Without kafka_auth nothing is added: what the environment says, if anything, stays.
    assert without.env("gateway").get("MAPSERVICE_KAFKA_USERNAME") == os.environ.get(
        "MAPSERVICE_KAFKA_USERNAME"
    )
    assert without.kafka_users() == ()


def test_kafka_credentials_on_tansu_are_refused_with_the_reason(tmp_path) -> None:
    with pytest.raises(ValueError, match="tansu has no SASL"):
        Stack(tmp_path, mqtt="mosquitto", kafka="tansu", kafka_auth=True)
