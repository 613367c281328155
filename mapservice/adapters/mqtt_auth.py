"""Robot identities at the MQTT broker: Mosquitto's password file and ACL file.

Every robot has its own MQTT user, named by its robotId, with a generated password. The
ACL lets a user publish only on topics that name it (`iot/coordinates/<username>`,
`iot/chunks/create/<username>`) and read the advertisements; the service's users read
what the gateway consumes and publish the advertisements. The 2019 chunk topic
(`iot/chunks/create`) names no robot, so it is closed to robots unless an operator opens
it for a named robot (`legacy_chunks`), which then may write chunks under any robotId,
as in 2019. A master control (a username `mapservice-master-<name>`) publishes `order` and
`instantActions` to every VDA 5050 vehicle and reads all their state, visualization,
connection and factsheet messages; vehicles still read only their own orders.

Shared subscriptions (`$share/...`), which the acl_file cannot refuse, are refused to every
user but the service's by a third file, the dynamic security plugin's (mosquitto_dynsec.py).

The files are Mosquitto's own formats (`password_file`, `acl_file`), written here without
`mosquitto_passwd` so that the production image needs no Mosquitto: passwords are hashed
as mosquitto_passwd 2.x does (`$7$`: PBKDF2-SHA512, 101 rounds, 12-byte salt; generated
passwords carry 192 bits, so the low round count costs nothing). Mosquitto reads both files
at start and on SIGHUP.
"""

from __future__ import annotations

import base64
import fcntl
import hashlib
import hmac
import os
import re
import secrets
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from mapservice.core.vda_ids import robot_id_for
from mapservice.settings import VDA5050_SUBTOPICS, Settings

from .mosquitto_dynsec import render_dynsec

GATEWAY_USER = "mapservice-gateway"
PROCESSORS_USER = "mapservice-processors"
RESERVED_PREFIX = "mapservice-"
PBKDF2_ROUNDS = 101  # what mosquitto_passwd 2.0 writes
_ROBOT_ID = re.compile(r"[A-Za-z0-9_.:@-]{1,64}")  # the gateway's robotId rule (wire2019)
# A VDA 5050 manufacturer or serial number as a level of a vehicle's username and topics.
_VEHICLE_NAME = re.compile(r"[^/+#:\x00-\x1f\x7f]{1,64}")
LEGACY_MARKER = "# --- robots allowed the 2019 chunk topic"
MASTER_MARKER = "# --- VDA 5050 master controls"
# A master control's username: under the service's reserved prefix, which no robot or
# vehicle may use (check_robot_id), so it never names a robot's topics.
MASTER_PREFIX = "mapservice-master-"
_MASTER = re.compile(re.escape(MASTER_PREFIX) + r"[A-Za-z0-9_.-]{1,40}")
MASTER_WRITES = ("order", "instantActions")


def new_password() -> str:
    """A generated MQTT password: 32 URL-safe characters (192 random bits)."""
    return secrets.token_urlsafe(24)


def hash_password(password: str, salt: bytes | None = None, rounds: int = PBKDF2_ROUNDS) -> str:
    """Mosquitto's `$7$` hash (what `mosquitto_passwd` 2.x writes)."""
    salt = salt if salt is not None else os.urandom(12)
    digest = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, rounds)
    return f"$7${rounds}${base64.b64encode(salt).decode()}${base64.b64encode(digest).decode()}"


def verify_password(password: str, hashed: str) -> bool:
    """Checks a password against a `$7$` (PBKDF2) or `$6$` (Mosquitto 1.x SHA-512) hash."""
    parts = hashed.split("$")
    try:
        if len(parts) == 5 and parts[1] == "7":
            rounds, salt, digest = (
                int(parts[2]),
                base64.b64decode(parts[3]),
                base64.b64decode(parts[4]),
            )
            computed = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, rounds)
        elif len(parts) == 4 and parts[1] == "6":
            salt, digest = base64.b64decode(parts[2]), base64.b64decode(parts[3])
            computed = hashlib.sha512(password.encode() + salt).digest()
        else:
            return False
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(computed, digest)


def vehicle_of_username(username: str) -> tuple[str, str] | None:
    """(manufacturer, serialNumber) of a VDA 5050 vehicle's MQTT username
    `<manufacturer>/<serialNumber>`; None for a 2019 robot's (a robotId has no slash)."""
    if username.count("/") != 1:
        return None
    manufacturer, serial = username.split("/")
    return (
        (manufacturer, serial)
        if _VEHICLE_NAME.fullmatch(manufacturer) and _VEHICLE_NAME.fullmatch(serial)
        else None
    )


def is_master_control(username: str) -> bool:
    return username.startswith(MASTER_PREFIX)


def check_master_control(username: str) -> None:
    if not _MASTER.fullmatch(username):
        raise ValueError(
            f"master control {username[:80]!r}: the username is {MASTER_PREFIX}<name>, "
            "the name 1-40 characters of A-Z a-z 0-9 _ . -"
        )


def check_robot_id(
    robot_id: str, service_users: tuple[str, ...] = (GATEWAY_USER, PROCESSORS_USER)
) -> None:
    """A robot's MQTT username is its robotId: the gateway's rule, and no service user's name;
    a VDA 5050 vehicle's is `<manufacturer>/<serialNumber>`, its topics' two levels."""
    if "/" in robot_id:
        names = vehicle_of_username(robot_id)
        if names is None:
            raise ValueError(
                f"VDA 5050 vehicle {robot_id[:80]!r}: the username is <manufacturer>/"
                "<serialNumber> as in its topics, each without / + # : or control characters "
                "(':' ends a name in Mosquitto's password file)"
            )
        if len(robot_id_for(*names)) > 64:
            raise ValueError(
                f"VDA 5050 vehicle {robot_id[:80]!r}: its robot id "
                f"{robot_id_for(*names)!r} is longer than 64 characters, so the "
                "gateway refuses its messages (bad_robot_id)"
            )
        return
    if not _ROBOT_ID.fullmatch(robot_id):
        raise ValueError(
            f"robot id {robot_id[:80]!r} must be 1-64 characters of A-Z a-z 0-9 _ . : @ - "
            "(the 2019 robotId rule the gateway checks)"
        )
    if robot_id in service_users:
        raise ValueError(f"{robot_id!r} is the service's own MQTT user, not a robot")
    if robot_id.startswith(RESERVED_PREFIX):
        # Where a robot's client id is its username, a robot named like a gateway's client
        # id (mapservice-gateway-0) could take over that gateway's session.
        raise ValueError(
            f"robot ids starting with {RESERVED_PREFIX!r} are reserved for the "
            "service's own clients"
        )


def check_identity(
    username: str, service_users: tuple[str, ...] = (GATEWAY_USER, PROCESSORS_USER)
) -> None:
    """A robot's, a vehicle's or a master control's MQTT username (robot add/remove)."""
    if is_master_control(username):
        check_master_control(username)
    else:
        check_robot_id(username, service_users)


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
                "reads": base + "{order,instantActions}",
                "robotId": robot_id_for(*names),
            }
        return {
            "pose": f"{self.coordinate_prefix}{robot_id}",
            "chunks": f"{self.robot_chunk_prefix}{robot_id}",
            "advertisements": self.advertisement_topic,
            **(
                {
                    "commands": f"{self.robot_root}{robot_id}/commands",
                    "commandEvents": f"{self.robot_root}{robot_id}/command-events",
                }
                if self.robot_root
                else {}
            ),
        }


def render_acl(
    topics: AclTopics,
    legacy_robots: list[str] = (),
    gateway_user: str = GATEWAY_USER,
    processors_user: str = PROCESSORS_USER,
    master_controls: list[str] = (),
) -> str:
    """Mosquitto's acl_file: `%u` patterns for every robot, the service's users, the VDA
    5050 master controls, and the robots an operator allowed on the 2019 chunk topic.
    Anything not listed is denied."""
    lines = [
        "# Mosquitto acl_file for mapservice, written by `mapservice robot add/remove`:",
        "# edits between the markers are overwritten. Anything not allowed here is denied.",
        "#",
        "# Every robot (its MQTT username is its robotId) publishes only on topics naming itself",
        "# and reads the map's and the operators' zones' advertisements.",
        f"pattern write {topics.coordinate_prefix}%u",
        f"pattern write {topics.robot_chunk_prefix}%u",
        f"pattern read {topics.advertisement_topic}",
        f"pattern read {topics.zone_advertisement_topic}",
        *(
            [
                "# Only the robot itself reads its commands and answers them (acks, outcomes).",
                f"pattern read {topics.robot_root}%u/commands",
                f"pattern write {topics.robot_root}%u/command-events",
            ]
            if topics.robot_root
            else []
        ),
        *(
            [
                "",
                "# Every VDA 5050 vehicle (its username is <manufacturer>/<serialNumber>, the two",
                "# levels of its topics) publishes only in its own subtree and reads its orders.",
                *(f"pattern write {topics.vda_interface}/+/%u/{sub}" for sub in VDA5050_SUBTOPICS),
                *(
                    f"pattern read {topics.vda_interface}/+/%u/{sub}"
                    for sub in ("order", "instantActions")
                ),
            ]
            if topics.vda_interface
            else []
        ),
        "",
        "# The gateway reads everything robots publish (also through $share/<group>/...).",
        f"user {gateway_user}",
        f"topic read {topics.coordinate_prefix}#",
        f"topic read {topics.robot_chunk_prefix}#",
        f"topic read {topics.legacy_chunk_topic}",
        *(
            [
                f"topic read {topics.vda_interface}/#",
                "# ... and sends a VDA 5050 vehicle its operators' commands as instant actions.",
                f"topic write {topics.vda_interface}/+/+/+/instantActions",
            ]
            if topics.vda_interface
            else []
        ),
        *(
            [
                f"topic read {topics.robot_root}+/command-events",
                "# ... and delivers the operators' commands, each on its robot's command topic.",
                f"topic write {topics.robot_root}+/commands",
            ]
            if topics.robot_root
            else []
        ),
        "",
        "# The processors announce each change of the latest map and of the zones.",
        f"user {processors_user}",
        f"topic write {topics.advertisement_topic}",
        f"topic write {topics.zone_advertisement_topic}",
        "",
        f"{MASTER_MARKER} (each orders every vehicle and reads all their messages;",
        "# `mapservice robot add mapservice-master-<name>`) ---",
    ]
    for master in sorted(set(master_controls)) if topics.vda_interface else ():
        lines += [
            f"user {master}",
            *(f"topic write {topics.vda_interface}/+/+/+/{sub}" for sub in MASTER_WRITES),
            *(f"topic read {topics.vda_interface}/+/+/+/{sub}" for sub in VDA5050_SUBTOPICS),
        ]
    lines += [
        "",
        f"{LEGACY_MARKER} ({topics.legacy_chunk_topic}, which names no robot: such a",
        "# robot may write chunks under any robotId; `mapservice robot add --legacy-chunks`) ---",
    ]
    for robot in sorted(set(legacy_robots)):
        lines += [f"user {robot}", f"topic write {topics.legacy_chunk_topic}"]
    return "\n".join(lines) + "\n"


def master_controls_in(acl_text: str) -> list[str]:
    """The master controls a rendered ACL names."""
    if MASTER_MARKER not in acl_text:
        return []
    section = acl_text.split(MASTER_MARKER, 1)[1].split(LEGACY_MARKER, 1)[0]
    return [
        line.split(None, 1)[1].strip() for line in section.splitlines() if line.startswith("user ")
    ]


def legacy_robots_in(acl_text: str) -> list[str]:
    """The robots a rendered ACL allows on the 2019 chunk topic."""
    if LEGACY_MARKER not in acl_text:
        return []
    section = acl_text.split(LEGACY_MARKER, 1)[1]
    return [
        line.split(None, 1)[1].strip() for line in section.splitlines() if line.startswith("user ")
    ]


def read_password_file(path: Path) -> dict[str, str]:
    """username -> hash, in file order."""
    users: dict[str, str] = {}
    if path.exists():
        for line in path.read_text().splitlines():
            if line.strip() and not line.startswith("#") and ":" in line:
                name, hashed = line.split(":", 1)
                users[name] = hashed.strip()
    return users


def _write_atomically(path: Path, text: str, mode: int) -> None:
    """Replaces `path` in one step; an existing file keeps its mode and owner (the broker's
    user must still read it), a new one gets `mode`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as file:
        file.write(text)
    try:
        old = path.stat()
    except FileNotFoundError:
        os.chmod(tmp, mode)
    else:
        os.chmod(tmp, old.st_mode & 0o7777)
        try:
            os.chown(tmp, old.st_uid, old.st_gid)
        except PermissionError:
            pass  # not ours to give away: the mode still says who may read it
    os.replace(tmp, path)  # a broker reloading meanwhile reads the old or the new file


@dataclass(frozen=True)
class RobotCredential:
    robot_id: str
    username: str
    password: str
    topics: dict[str, str]
    legacy_chunks: bool = False


@dataclass
class BrokerFiles:
    """A Mosquitto password file and ACL file, changed under a lock (two `robot add` at once
    do not lose each other's users)."""

    password_file: Path
    acl_file: Path
    topics: AclTopics = field(default_factory=AclTopics)
    gateway_user: str = GATEWAY_USER
    processors_user: str = PROCESSORS_USER

    @classmethod
    def in_data_dir(cls, data_dir: Path, settings: Settings | None = None) -> BrokerFiles:
        """The embedded mode's files: DATA_DIR/mqtt/passwd and DATA_DIR/mqtt/acl."""
        topics = AclTopics.from_settings(settings) if settings else AclTopics()
        return cls(Path(data_dir) / "mqtt" / "passwd", Path(data_dir) / "mqtt" / "acl", topics)

    @property
    def service_users(self) -> tuple[str, str]:
        return self.gateway_user, self.processors_user

    @property
    def dynsec_file(self) -> Path:
        """The dynamic security plugin's file, beside the ACL (`<acl>.dynsec.json`)."""
        return self.acl_file.with_name(f"{self.acl_file.name}.dynsec.json")

    @contextmanager
    def _locked(self):
        self.password_file.parent.mkdir(parents=True, exist_ok=True)
        with open(self.password_file.with_name(f".{self.password_file.name}.lock"), "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            yield

    def _write(self, users: dict[str, str], legacy: list[str]) -> None:
        # 0600 when the file holds only hashes: Mosquitto warns about readable password files.
        _write_atomically(
            self.password_file, "".join(f"{u}:{h}\n" for u, h in users.items()), 0o600
        )
        # The master controls are the users under their prefix: the ACL follows the users.
        masters = [u for u in users if is_master_control(u)]
        _write_atomically(
            self.acl_file,
            render_acl(self.topics, legacy, self.gateway_user, self.processors_user, masters),
            0o644,
        )
        _write_atomically(
            self.dynsec_file,
            render_dynsec(u for u in users if u not in self.service_users),
            0o644,
        )

    def _legacy(self) -> list[str]:
        return legacy_robots_in(self.acl_file.read_text()) if self.acl_file.exists() else []

    def robots(self) -> list[str]:
        """Robot users (every user but the service's), in file order; master controls too
        (`master_controls()` says which)."""
        return [u for u in read_password_file(self.password_file) if u not in self.service_users]

    def master_controls(self) -> list[str]:
        return master_controls_in(self.acl_file.read_text()) if self.acl_file.exists() else []

    def legacy_robots(self) -> list[str]:
        return self._legacy()

    def ensure(self) -> None:
        """Writes both files if missing (a broker needs them to start), keeping what is there."""
        with self._locked():
            self._write(read_password_file(self.password_file), self._legacy())

    def set_service_user(self, username: str, password: str) -> None:
        if username not in self.service_users:
            raise ValueError(f"{username!r} is not one of the service users {self.service_users}")
        with self._locked():
            users = read_password_file(self.password_file)
            users[username] = hash_password(password)
            self._write(users, self._legacy())

    def add_robot(
        self,
        robot_id: str,
        *,
        legacy_chunks: bool = False,
        rotate: bool = False,
        password: str | None = None,
    ) -> RobotCredential:
        """Adds a robot user (or, with `rotate`, gives an existing one a new password) and
        returns its credential; the password is not stored anywhere but as a hash. A
        username `mapservice-master-<name>` is a VDA 5050 master control's."""
        check_identity(robot_id, self.service_users)
        if legacy_chunks and (vehicle_of_username(robot_id) or is_master_control(robot_id)):
            raise ValueError(
                "--legacy-chunks is for 2019 robots, not VDA 5050 vehicles or master controls"
            )
        password = password or new_password()
        with self._locked():
            users = read_password_file(self.password_file)
            if robot_id in users and not rotate:
                raise ValueError(
                    f"robot {robot_id!r} already has an MQTT credential; "
                    "--rotate gives it a new password"
                )
            users[robot_id] = hash_password(password)
            legacy = [r for r in self._legacy() if r != robot_id or legacy_chunks]
            if legacy_chunks:
                legacy.append(robot_id)
            self._write(users, legacy)
        return RobotCredential(
            robot_id, robot_id, password, self.topics.robot_topics(robot_id), legacy_chunks
        )

    def remove_robot(self, robot_id: str) -> bool:
        """Removes a robot's user (it can no longer connect once the broker reloaded)."""
        check_identity(robot_id, self.service_users)
        with self._locked():
            users = read_password_file(self.password_file)
            legacy = self._legacy()
            if robot_id not in users and robot_id not in legacy:
                return False
            users.pop(robot_id, None)
            self._write(users, [r for r in legacy if r != robot_id])
        return True
