"""Mosquitto's acl_file, rendered from the access policy (mqtt_policy.py).

A robot's and a vehicle's rows are `pattern` lines with `%u` (Mosquitto applies a pattern to
every user, whatever its kind), the service's users', each master control's and each robot
allowed the 2019 chunk topic are `user` sections. `read` is Mosquitto's word for receiving
(it checks each message at delivery, not the SUBSCRIBE), `write` for publishing. Anything not
listed is denied.
"""

from __future__ import annotations

from collections.abc import Iterable

from .mqtt_policy import (
    GATEWAY_USER,
    ME,
    PROCESSORS_USER,
    AclTopics,
    Action,
    Identity,
    Rule,
    access_policy,
    rules_of,
)

LEGACY_MARKER = "# --- robots allowed the 2019 chunk topic"
MASTER_MARKER = "# --- VDA 5050 master controls"
_VERB = {Action.PUBLISH: "write", Action.SUBSCRIBE: "read"}


def _patterns(rules: Iterable[Rule]) -> list[str]:
    return [f"pattern {_VERB[r.action]} {r.topic_filter.replace(ME, '%u')}" for r in rules]


def _user(username: str, rules: Iterable[Rule]) -> list[str]:
    return [f"user {username}", *(f"topic {_VERB[r.action]} {r.for_user(username)}" for r in rules)]


def render_acl(
    topics: AclTopics,
    legacy_robots: Iterable[str] = (),
    gateway_user: str = GATEWAY_USER,
    processors_user: str = PROCESSORS_USER,
    master_controls: Iterable[str] = (),
) -> str:
    """Mosquitto's acl_file: `%u` patterns for every robot and vehicle, the service's users,
    the VDA 5050 master controls, and the robots an operator allowed on the 2019 chunk
    topic. Anything not listed is denied."""
    policy = access_policy(topics)
    lines = [
        "# Mosquitto acl_file for mapservice, written by `mapservice robot add/remove`:",
        "# edits between the markers are overwritten. Anything not allowed here is denied.",
        "#",
        "# Every robot (its MQTT username is its robotId) publishes only on topics naming itself",
        "# and reads its own commands; every user reads the advertisements.",
        *_patterns(rules_of(policy, Identity.ROBOT, Identity.EVERYONE)),
    ]
    if vehicle_rules := rules_of(policy, Identity.VEHICLE):
        lines += [
            "",
            "# Every VDA 5050 vehicle (its username is <manufacturer>/<serialNumber>, the two",
            "# levels of its topics) publishes only in its own subtree and reads its orders.",
            *_patterns(vehicle_rules),
        ]
    lines += [
        "",
        "# The gateway reads everything robots publish (also through $share/<group>/...) and",
        "# delivers the operators' commands (a vehicle's as instant actions).",
        *_user(gateway_user, rules_of(policy, Identity.GATEWAY)),
        "",
        "# The processors announce each change of the latest map and of the zones, and incidents.",
        *_user(processors_user, rules_of(policy, Identity.PROCESSORS)),
        "",
        f"{MASTER_MARKER} (each orders every vehicle and reads all their messages;",
        "# `mapservice robot add mapservice-master-<name>`) ---",
    ]
    master_rules = rules_of(policy, Identity.MASTER)
    for master in sorted(set(master_controls)) if master_rules else ():
        lines += _user(master, master_rules)
    lines += [
        "",
        f"{LEGACY_MARKER} ({topics.legacy_chunk_topic}, which names no robot: such a",
        "# robot may write chunks under any robotId; `mapservice robot add --legacy-chunks`) ---",
    ]
    for robot in sorted(set(legacy_robots)):
        lines += _user(robot, rules_of(policy, Identity.LEGACY_CHUNKS))
    return "\n".join(lines) + "\n"


def _users_after(marker: str, acl_text: str, end: str | None = None) -> list[str]:
    if marker not in acl_text:
        return []
    section = acl_text.split(marker, 1)[1]
    section = section.split(end, 1)[0] if end else section
    return [
        line.split(None, 1)[1].strip() for line in section.splitlines() if line.startswith("user ")
    ]


def master_controls_in(acl_text: str) -> list[str]:
    """The master controls a rendered ACL names."""
    return _users_after(MASTER_MARKER, acl_text, LEGACY_MARKER)


def legacy_robots_in(acl_text: str) -> list[str]:
    """The robots a rendered ACL allows on the 2019 chunk topic."""
    return _users_after(LEGACY_MARKER, acl_text)
