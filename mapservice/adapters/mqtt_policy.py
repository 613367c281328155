"""Who may publish and subscribe where at the MQTT broker: one table, rendered per broker.

The table is written once here, as rows of (identity, action, topic filter); Mosquitto's
acl_file (mosquitto_acl.py) and EMQX's ACL file (emqx_acl.py) are renderings of it, and
tests read each rendering back against it. An identity is a kind of MQTT user:

- a robot (2019 contract): its username is its robotId;
- a VDA 5050 vehicle: its username is `<manufacturer>/<serialNumber>`, two levels of its topics;
- a master control: a username `mapservice-master-<name>`;
- everyone: any authenticated user (the map's advertisements, on the 2019 topic and on the
  area topics, and the zones' are public);
- the gateway and the processors: the service's own users;
- a robot an operator let use the 2019 chunk topic (named one by one; that topic carries no
  robotId, so such a robot may write chunks under any robotId).

`{me}` in a filter stands for the user's own username (Mosquitto's `%u`, EMQX's
`${username}`); a row with it is a pattern every user of the identity gets for itself.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import Enum

from mapservice.core.areas import area_topic_filter
from mapservice.core.vda_ids import robot_id_for
from mapservice.settings import VDA5050_SUBTOPICS, Settings

ME = "{me}"
GATEWAY_USER = "mapservice-gateway"
PROCESSORS_USER = "mapservice-processors"
RESERVED_PREFIX = "mapservice-"
# A master control's username: under the service's reserved prefix, which no robot or
# vehicle may use (check_robot_id), so it never names a robot's topics.
MASTER_PREFIX = "mapservice-master-"
MASTER_WRITES = ("order", "instantActions")
VEHICLE_READS = ("order", "instantActions")

# The username rules, as regular expressions both brokers' renderings use.
ROBOT_USERNAME = r"[A-Za-z0-9_.:@-]{1,64}"  # the gateway's robotId rule (wire2019)
MASTER_USERNAME = MASTER_PREFIX + r"[A-Za-z0-9_.-]{1,40}"  # the prefix has no special character
# A VDA 5050 manufacturer or serial number as a level of a vehicle's username and topics.
VEHICLE_NAME = r"[^/+#:\x00-\x1f\x7f]{1,64}"


class Identity(Enum):
    ROBOT = "robot"
    VEHICLE = "vehicle"
    MASTER = "master control"
    EVERYONE = "every user"
    GATEWAY = "gateway"
    PROCESSORS = "processors"
    LEGACY_CHUNKS = "robot allowed the 2019 chunk topic"


class Action(Enum):
    PUBLISH = "publish"
    SUBSCRIBE = "subscribe"


@dataclass(frozen=True)
class Rule:
    identity: Identity
    action: Action
    topic_filter: str  # `{me}`: the user's own username

    def for_user(self, username: str) -> str:
        return self.topic_filter.replace(ME, username)


def vehicle_of_username(username: str) -> tuple[str, str] | None:
    """(manufacturer, serialNumber) of a VDA 5050 vehicle's MQTT username
    `<manufacturer>/<serialNumber>`; None for a 2019 robot's (a robotId has no slash)."""
    if username.count("/") != 1:
        return None
    manufacturer, serial = username.split("/")
    return (
        (manufacturer, serial)
        if re.fullmatch(VEHICLE_NAME, manufacturer) and re.fullmatch(VEHICLE_NAME, serial)
        else None
    )


def is_master_control(username: str) -> bool:
    return username.startswith(MASTER_PREFIX)


@dataclass(frozen=True)
class AclTopics:
    """The topics the ACL is about, as the service is configured."""

    coordinate_prefix: str = "iot/coordinates/"
    robot_chunk_prefix: str = "iot/chunks/create/"
    legacy_chunk_topic: str = "iot/chunks/create"
    advertisement_topic: str = "iot/chunks/advertisement"
    vda_interface: str = (
        "uagv"  # VDA 5050 vehicles' topics: <interface>/<major>/<manufacturer>/<serial>/...
    )
    robot_root: str = "iot/robots/"  # <root><robotId>/commands (read), .../command-events (write)
    zone_advertisement_topic: str = "iot/zones/advertisement"
    incident_alert_root: str = "iot/incidents/"  # <root><kind>: the processors' incident alerts

    @property
    def area_advertisement_filter(self) -> str:
        """Every advertisement area's topic (core/areas.py)."""
        return area_topic_filter(self.advertisement_topic)

    @classmethod
    def from_settings(cls, settings: Settings) -> AclTopics:
        def prefix(topic_filter: str) -> str:
            return topic_filter.rstrip("#+").rstrip("/") + "/"

        return cls(
            prefix(settings.coordinate_topic),
            prefix(settings.robot_chunk_topic or "iot/chunks/create/+"),
            settings.create_chunk_topic or "iot/chunks/create",
            settings.advertisement_topic,
            settings.vda5050_interface,
            settings.robot_topic_root.rstrip("/") + "/" if settings.robot_topic_root else "",
            settings.zone_advertisement_topic,
            prefix(settings.incident_alert_topic_root),
        )

    def robot_topics(self, robot_id: str) -> dict[str, str]:
        """What a robot publishes to (and reads), for its configuration."""
        if is_master_control(robot_id):
            base = f"{self.vda_interface}/+/+/+/"
            return {
                "publishes": base + "{" + ",".join(MASTER_WRITES) + "}",
                "reads": base + "{" + ",".join(VDA5050_SUBTOPICS) + "}",
                "masterControl": "yes",
            }
        if (names := vehicle_of_username(robot_id)) is not None:
            base = f"{self.vda_interface}/<v2|v3>/{names[0]}/{names[1]}/"
            return {
                "publishes": base + "{" + ",".join(VDA5050_SUBTOPICS) + "}",
                "reads": base + "{" + ",".join(VEHICLE_READS) + "}",
                "robotId": robot_id_for(*names),
            }
        return {
            "pose": f"{self.coordinate_prefix}{robot_id}",
            "chunks": f"{self.robot_chunk_prefix}{robot_id}",
            "advertisements": self.advertisement_topic,
            "areaAdvertisements": self.area_advertisement_filter,
            **(
                {
                    "commands": f"{self.robot_root}{robot_id}/commands",
                    "commandEvents": f"{self.robot_root}{robot_id}/command-events",
                }
                if self.robot_root
                else {}
            ),
        }


def access_policy(topics: AclTopics) -> tuple[Rule, ...]:
    """The table: every (identity, action, topic filter) the broker allows; nothing else is."""
    robot, vehicle, master = Identity.ROBOT, Identity.VEHICLE, Identity.MASTER
    pub, sub = Action.PUBLISH, Action.SUBSCRIBE
    vda, root = topics.vda_interface, topics.robot_root
    rows: list[Rule] = [
        # A robot publishes only on topics naming itself; the gateway also checks the
        # payload's robotId against the topic's.
        Rule(robot, pub, f"{topics.coordinate_prefix}{ME}"),
        Rule(robot, pub, f"{topics.robot_chunk_prefix}{ME}"),
        # Only the robot itself reads its commands and answers them (acks, outcomes).
        *(
            [
                Rule(robot, sub, f"{root}{ME}/commands"),
                Rule(robot, pub, f"{root}{ME}/command-events"),
            ]
            if root
            else []
        ),
        # Everyone learns of each change of the latest map (the whole plant's, or an
        # area's) and of the operators' zones.
        Rule(Identity.EVERYONE, sub, topics.advertisement_topic),
        Rule(Identity.EVERYONE, sub, topics.area_advertisement_filter),
        Rule(Identity.EVERYONE, sub, topics.zone_advertisement_topic),
        # The plant's systems hear of the incidents as a master control (which reads every
        # vehicle's messages anyway): an incident names robots and where they were, which
        # no robot may learn of another; no robot may raise or fake one.
        Rule(master, sub, f"{topics.incident_alert_root}+"),
    ]
    if vda:
        rows += [
            # A vehicle publishes only in its own subtree and reads its own orders.
            *(Rule(vehicle, pub, f"{vda}/+/{ME}/{s}") for s in VDA5050_SUBTOPICS),
            *(Rule(vehicle, sub, f"{vda}/+/{ME}/{s}") for s in VEHICLE_READS),
            # A master control orders every vehicle and reads all their messages.
            *(Rule(master, pub, f"{vda}/+/+/+/{s}") for s in MASTER_WRITES),
            *(Rule(master, sub, f"{vda}/+/+/+/{s}") for s in VDA5050_SUBTOPICS),
        ]
    # The gateway reads everything robots publish (the filters it subscribes to) ...
    rows += [
        Rule(Identity.GATEWAY, sub, topic)
        for topic in (
            f"{topics.coordinate_prefix}#",
            f"{topics.robot_chunk_prefix}+",
            topics.legacy_chunk_topic,
            *(f"{vda}/+/+/+/{s}" for s in VDA5050_SUBTOPICS if vda),
            *([f"{root}+/command-events"] if root else []),
        )
    ]
    # ... and delivers the operators' commands: on a robot's command topic, or to a vehicle
    # as instant actions.
    rows += [
        Rule(Identity.GATEWAY, pub, topic)
        for topic in (
            *([f"{root}+/commands"] if root else []),
            *([f"{vda}/+/+/+/instantActions"] if vda else []),
        )
    ]
    # The processors announce each change of the latest map and of the zones, and the incidents.
    rows += [
        Rule(Identity.PROCESSORS, pub, topics.advertisement_topic),
        Rule(Identity.PROCESSORS, pub, topics.area_advertisement_filter),
        Rule(Identity.PROCESSORS, pub, topics.zone_advertisement_topic),
        Rule(Identity.PROCESSORS, pub, f"{topics.incident_alert_root}+"),
        Rule(Identity.LEGACY_CHUNKS, pub, topics.legacy_chunk_topic),
    ]
    return tuple(rows)


def rules_of(rules: tuple[Rule, ...], *identities: Identity) -> list[Rule]:
    return [rule for rule in rules if rule.identity in identities]
