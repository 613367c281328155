"""The incident alerts' topics in the MQTT access policy, as each broker's rendering says it:
for every kind, the processors may publish and a master control (the plant's systems) may
subscribe; no robot, vehicle or the gateway may read one (an incident names other robots and
where they were), and none of them or a master control may publish one (EMQX's acl.conf evaluated as EMQX
does; Mosquitto's acl_file read line by line: a real Mosquitto checks it in
tests/processors/test_incident_alerts_mqtt.py)."""

from __future__ import annotations

import pytest

from mapservice.adapters.emqx_acl import render_emqx_acl
from mapservice.adapters.mosquitto_acl import render_acl
from mapservice.adapters.mqtt_policy import GATEWAY_USER, PROCESSORS_USER, AclTopics
from mapservice.core.incident_alerts import alert_topic
from mapservice.core.incident_model import KINDS
from mapservice.settings import Settings
from tests.fixtures.emqx_acl_eval import emqx_allows, rule_lines
from tests.fixtures.mqtt_policy_cases import MASTER, ROBOTS, VEHICLES

OTHERS = (*ROBOTS, *VEHICLES, MASTER, GATEWAY_USER)
NOT_READING = (*ROBOTS, *VEHICLES, GATEWAY_USER)
ROOTS = ("iot/incidents/", "site1/alerts/incidents")  # the default and a configured one


@pytest.mark.parametrize("root", ROOTS)
@pytest.mark.parametrize("kind", KINDS)
def test_emqx_lets_only_the_processors_publish_incidents_and_master_controls_read_them(
    kind: str, root: str
) -> None:
    topics = AclTopics.from_settings(Settings(incident_alert_topic_root=root))
    rules = rule_lines(render_emqx_acl(topics))
    topic = alert_topic(root, kind)
    assert emqx_allows(rules, PROCESSORS_USER, "publish", topic)
    for user in OTHERS:
        assert not emqx_allows(rules, user, "publish", topic), user
    assert emqx_allows(rules, MASTER, "subscribe", topic)
    assert emqx_allows(rules, MASTER, "subscribe", alert_topic(root, "+"))
    for user in NOT_READING:
        assert not emqx_allows(rules, user, "subscribe", topic), user
        assert not emqx_allows(rules, user, "subscribe", alert_topic(root, "+")), user


@pytest.mark.parametrize("root", ROOTS)
def test_mosquitto_lets_only_the_processors_write_incidents_and_master_controls_read_them(
    root: str,
) -> None:
    topics = AclTopics.from_settings(Settings(incident_alert_topic_root=root))
    lines = render_acl(topics, master_controls=[MASTER]).splitlines()
    incident_filter = alert_topic(root, "+")
    granting = [line for line in lines if line.endswith(f" {incident_filter}")]
    assert f"pattern read {incident_filter}" not in granting  # not every user
    reads = [line for line in granting if line.startswith("topic read ")]
    assert reads == [f"topic read {incident_filter}"]
    master = lines[lines.index(f"user {MASTER}") :]
    assert (
        f"topic read {incident_filter}"
        in master[
            : next(
                (n for n, line in enumerate(master[1:], 1) if line.startswith("user ")), len(master)
            )
        ]
    )
    writes = [line for line in granting if " write " in line or " readwrite " in line]
    assert writes == [f"topic write {incident_filter}"]
    # that write is in the processors' section
    section = lines[lines.index(f"user {PROCESSORS_USER}") :]
    assert f"topic write {incident_filter}" in section
    assert not any(line.startswith("user ") for line in section[1 : section.index(writes[0])])
