"""Robot identities at the MQTT broker: Mosquitto's password file and ACL file.

Every robot, VDA 5050 vehicle and master control has its own MQTT user with a generated
password; what each may publish and read is the access policy (mqtt_policy.py), which the
ACL file renders (mosquitto_acl.py). The 2019 chunk topic (`iot/chunks/create`) names no
robot, so it is closed to robots unless an operator opens it for a named robot
(`legacy_chunks`), which then may write chunks under any robotId, as in 2019.

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
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from mapservice.core.vda_ids import robot_id_for
from mapservice.settings import Settings

from .mosquitto_acl import legacy_robots_in, master_controls_in, render_acl
from .mosquitto_dynsec import render_dynsec
from .mqtt_policy import (
    GATEWAY_USER,
    MASTER_PREFIX,
    MASTER_USERNAME,
    PROCESSORS_USER,
    RESERVED_PREFIX,
    ROBOT_USERNAME,
    AclTopics,
    is_master_control,
    vehicle_of_username,
)

__all__ = [
    "GATEWAY_USER",
    "PROCESSORS_USER",
    "AclTopics",
    "BrokerFiles",
    "RobotCredential",
    "check_identity",
    "hash_password",
    "is_master_control",
    "legacy_robots_in",
    "master_controls_in",
    "new_password",
    "render_acl",
    "vehicle_of_username",
    "verify_password",
]

PBKDF2_ROUNDS = 101  # what mosquitto_passwd 2.0 writes
_ROBOT_ID = re.compile(ROBOT_USERNAME)
_MASTER = re.compile(MASTER_USERNAME)


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
    def _locked(self) -> Iterator[None]:
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
