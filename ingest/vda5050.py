"""VDA 5050 vehicles: `state`, `visualization`, `connection` and `factsheet` messages on
`<interface>/<major>/<manufacturer>/<serialNumber>/<subtopic>` become history events.

Each message is validated against the official schema of its version (vendored, with its
licence, in vda5050_schemas/), its manufacturer and serial number must be its topic's, and
the vehicle becomes the robot `robot_id_for(manufacturer, serial)`. A `visualization` pose
carries the battery and status of the vehicle's last `state` (held here, per vehicle),
so its history rows are not NULL for them.
"""

from __future__ import annotations

import json
import math
from functools import cache
from pathlib import Path

import jsonschema_rs
import msgspec
from cachetools import LRUCache
from jsonschema import Draft202012Validator
from jsonschema.exceptions import ValidationError, best_match

from mapservice.core.events import (
    Envelope,
    PoseReported,
    VdaConnectionReported,
    VdaError,
    VdaFactsheetReported,
    VdaStateReported,
    make_envelope,
)
from mapservice.core.vda_ids import robot_id_for
from mapservice.core.wire2019 import (
    MAX_ABS_METRES,
    Limits,
    Reason,
    Rejection,
    check_time,
    finite,
)
from mapservice.settings import VDA5050_SUBTOPICS

SCHEMA_DIR = Path(__file__).with_name("vda5050_schemas")
SUBTOPICS = VDA5050_SUBTOPICS
MAX_VEHICLES = 100_000  # vehicles whose last state is held for their visualization poses


@cache
def patched_schema(version: str, subtopic: str) -> dict:
    """The vendored schema of the version and subtopic, with its errata corrected: what
    both validators below check."""
    schema = json.loads((SCHEMA_DIR / version / f"{subtopic}.schema").read_text())
    if (version, subtopic) == ("2.0.0", "state"):
        # Erratum: 2.0.0's state schema requires theta in a nodeState's nodePosition,
        # where the order's nodePosition (which the vehicle echoes) has it optional, and
        # 2.1.0's schema requires only x, y and mapId; vehicles written against 2.0 omit
        # it (npm vda-5050-lib does), so their states during an order would all be refused.
        node_position = schema["properties"]["nodeStates"]["items"]["properties"]["nodePosition"]
        node_position["required"] = [k for k in node_position["required"] if k != "theta"]
    if (version, subtopic) == ("2.0.0", "instantActions"):
        # Erratum: 2.0.0's schema names the list `actions` and its entries' `actionName`,
        # and requires no header; the 2.0 specification (and npm vda-5050-lib's 2.0
        # vehicles) has `instantActions` with `actionType`, and 2.1.0's schema requires
        # the header. Checked as the specification says, with the schema's action object.
        props = schema["properties"]
        props["instantActions"] = props.pop("actions")
        action = props["instantActions"]["items"]
        action["properties"]["actionType"] = action["properties"].pop("actionName")
        action["required"] = ["actionId", "actionType", "blockingType"]
        schema["required"] = [
            "headerId",
            "timestamp",
            "version",
            "manufacturer",
            "serialNumber",
            "instantActions",
        ]
    return schema


@cache
def validator(version: str, subtopic: str) -> Draft202012Validator:
    """The reference validator: its best match is a refused message's reason."""
    return Draft202012Validator(patched_schema(version, subtopic))


@cache
def compiled_validator(version: str, subtopic: str) -> jsonschema_rs.Validator:
    """The same schema compiled (Rust): a valid message costs a few microseconds here,
    against 60-120 in the reference validator, which names no formats' checker, so
    neither does this one (`date-time` stays an annotation)."""
    return jsonschema_rs.Draft202012Validator(
        patched_schema(version, subtopic), validate_formats=False
    )


def schema_error(version: str, subtopic: str, msg: dict) -> ValidationError | None:
    """Why the message is not valid against its schema, or None. The compiled validator
    passes the valid ones; the reference validator judges the rest and words the reason,
    so where the two disagree (a NaN is a number to it, say) the verdict is today's."""
    try:
        if compiled_validator(version, subtopic).is_valid(msg):
            return None
    except ValueError:
        pass  # a value the compiled validator cannot take: the reference one judges it
    return best_match(validator(version, subtopic).iter_errors(msg))


def _refuse_constant(name: str) -> float:
    # Python's json reads NaN and Infinity, which JSON (RFC 8259) has no token for and
    # which no pose, battery or path point may hold.
    raise ValueError(f"{name} is not a JSON number")


def _storable_numbers(msg: dict) -> bool:
    """Whether the numbers a state or visualization puts into the history are finite and
    within the floor's bounds (a number too large for a float, like 1e400, reads as inf)."""
    position = msg.get("agvPosition") or msg.get("mobileRobotPosition") or {}
    power = msg.get("powerSupply") or msg.get("batteryState") or {}
    values = [
        position.get("x"),
        position.get("y"),
        position.get("theta"),
        power.get("batteryCharge", power.get("stateOfCharge")),
    ]
    for node in msg.get("nodeStates", ()):
        values += [node.get("nodePosition", {}).get(k) for k in ("x", "y")]
    planned = msg.get("plannedPath") or {}
    for point in planned.get("trajectory", {}).get("controlPoints", ()):
        values += [point.get("x"), point.get("y")]
    try:
        return finite(*(None if v is None else float(v) for v in values))
    except (OverflowError, TypeError, ValueError):
        return False  # an integer beyond any float


def schema_version_for(version: object, topic_major: str) -> str | None:
    """The vendored schema for a message's `version` ("2.0.x", "2.1.x", "3.0.x"), if its
    major matches the topic's (`v2`)."""
    if not isinstance(version, str):
        return None
    parts = version.split(".")
    if len(parts) < 2 or f"v{parts[0]}" != topic_major:
        return None
    return {("2", "0"): "2.0.0", ("2", "1"): "2.1.0", ("3", "0"): "3.0.0"}.get((parts[0], parts[1]))


Transform = tuple[float, float, float]  # dx, dy (metres), rotation (radians)


class _Status(msgspec.Struct, frozen=True, gc=False):
    """What a vehicle's last `state` said, carried onto its visualization poses."""

    battery: float | None
    charging: bool | None
    loaded: bool | None
    path: tuple[tuple[float, float], ...] | None
    driving: bool | None
    paused: bool | None
    operating_mode: str
    order_id: str


class VdaIngest:
    """Turns one VDA 5050 message into an event or a Rejection."""

    def __init__(self, interface: str, map_transforms: dict[str, Transform]) -> None:
        self.interface = interface
        self.prefix = interface + "/"
        self.map_transforms = dict(map_transforms)
        self.last_status: LRUCache[str, _Status] = LRUCache(MAX_VEHICLES)

    def handles(self, mqtt_topic: str) -> bool:
        return bool(self.interface) and mqtt_topic.startswith(self.prefix)

    def decode(
        self, mqtt_topic: str, payload: bytes, receive_ms: int, limits: Limits
    ) -> Envelope | Rejection:
        return self.decode_message(mqtt_topic, payload, receive_ms, limits)[0]

    def decode_message(
        self, mqtt_topic: str, payload: bytes, receive_ms: int, limits: Limits
    ) -> tuple[Envelope | Rejection, dict | None]:
        """decode's result, with the message as parsed once it is valid against its schema
        (the router reads a state's actionStates from it without parsing it again)."""
        checked = self._schema_checked(mqtt_topic, payload, limits)
        if isinstance(checked, Rejection):
            return checked, None
        msg = checked[-1]
        return self._event(*checked, receive_ms, limits), msg

    def _schema_checked(
        self, mqtt_topic: str, payload: bytes, limits: Limits
    ) -> tuple[str, str, str, str, dict] | Rejection:
        """(manufacturer, serial, subtopic, schema version, message) of a message valid
        against its version's schema on a well-formed topic."""
        levels = mqtt_topic.split("/")
        if len(levels) != 5 or levels[4] not in SUBTOPICS or not all(levels):
            return Rejection(
                Reason.UNKNOWN_TOPIC,
                (
                    f"VDA 5050 topics are {self.interface}/<major>/<manufacturer>/<serialNumber>/"
                    f"<{'|'.join(SUBTOPICS)}>, not {mqtt_topic[:200]!r}"
                ),
            )
        _, major, manufacturer, serial, subtopic = levels
        if len(payload) > limits.max_message_bytes:
            return Rejection(
                Reason.OVERSIZED,
                f"{len(payload)} bytes; at most {limits.max_message_bytes} are accepted",
            )
        try:
            msg = json.loads(payload, parse_constant=_refuse_constant)
        except (ValueError, RecursionError) as exc:
            return Rejection(Reason.NOT_JSON, f"not JSON: {str(exc)[:200]}")
        if not isinstance(msg, dict):
            return Rejection(Reason.WRONG_TYPE, "a VDA 5050 message is a JSON object")
        version = schema_version_for(msg.get("version"), major)
        if version is None:
            return Rejection(
                Reason.VDA_UNSUPPORTED_VERSION,
                (
                    f"version {str(msg.get('version'))[:40]!r} on topic major {major[:20]!r}: "
                    "2.0.x, 2.1.x (topic v2) and 3.0.x (topic v3) are accepted"
                ),
            )
        error = schema_error(version, subtopic, msg)
        if error is not None:
            where = "/".join(str(p) for p in error.absolute_path) or "(message)"
            return Rejection(
                Reason.VDA_SCHEMA,
                (f"not a valid VDA 5050 {version} {subtopic}: at {where}: {error.message[:300]}"),
            )
        return manufacturer, serial, subtopic, version, msg

    def _event(
        self,
        manufacturer: str,
        serial: str,
        subtopic: str,
        version: str,
        msg: dict,
        receive_ms: int,
        limits: Limits,
    ) -> Envelope | Rejection:
        for key in ("manufacturer", "serialNumber", "timestamp"):
            # 2.0.0's visualization schema requires none of its header.
            if not isinstance(msg.get(key), str):
                return Rejection(Reason.MISSING_FIELD, f"{key} (a string) is required")
        if msg["manufacturer"] != manufacturer or msg["serialNumber"] != serial:
            return Rejection(
                Reason.ROBOT_ID_MISMATCH,
                (
                    f"payload names {msg['manufacturer'][:60]!r}/{msg['serialNumber'][:60]!r}, its "
                    f"topic {manufacturer[:60]!r}/{serial[:60]!r}: a vehicle publishes only its own"
                ),
            )
        robot_id = robot_id_for(manufacturer, serial)
        if len(robot_id) > 64:
            return Rejection(
                Reason.BAD_ROBOT_ID,
                (
                    f"manufacturer and serial number make the robot id {robot_id[:80]!r}, longer "
                    "than 64 characters (escaped: see README, VDA 5050 vehicles)"
                ),
            )
        sent_ms = check_time(msg["timestamp"], receive_ms, limits)
        if isinstance(sent_ms, Rejection):
            return sent_ms
        if subtopic in ("state", "visualization") and not _storable_numbers(msg):
            return Rejection(
                Reason.OUT_OF_RANGE,
                (
                    "position, battery charge and path points must be finite and below "
                    f"{MAX_ABS_METRES:g} m"
                ),
            )
        if subtopic == "connection":
            state = msg["connectionState"]
            # The last will was composed at connect time: it went offline when published.
            at = receive_ms if state == "CONNECTIONBROKEN" else sent_ms
            return make_envelope(
                robot_id,
                at,
                receive_ms,
                VdaConnectionReported(manufacturer, serial, version, state, sent_ms),
            )
        if subtopic == "factsheet":
            return make_envelope(
                robot_id,
                sent_ms,
                receive_ms,
                VdaFactsheetReported(
                    manufacturer, serial, version, json.dumps(msg, separators=(",", ":"))
                ),
            )
        if subtopic == "state":
            return self._state(robot_id, version, msg, sent_ms, receive_ms)
        return self._visualization(robot_id, version, msg, sent_ms, receive_ms)

    def _state(
        self, robot_id: str, version: str, msg: dict, sent_ms: int, receive_ms: int
    ) -> Envelope:
        power = msg.get("powerSupply") or msg.get("batteryState") or {}
        loads = msg.get("loads")
        status = _Status(
            battery=float(power["batteryCharge" if "batteryCharge" in power else "stateOfCharge"])
            if power
            else None,
            charging=power.get("charging"),
            loaded=None if loads is None else bool(loads),
            path=self._path(msg),
            driving=msg.get("driving"),
            paused=msg.get("paused"),
            operating_mode=msg.get("operatingMode", ""),
            order_id=msg.get("orderId", ""),
        )
        self.last_status[robot_id] = status
        errors = tuple(
            VdaError(e.get("errorLevel", ""), e.get("errorType", ""), e.get("errorDescription", ""))
            for e in msg.get("errors", ())
        )
        return make_envelope(
            robot_id, sent_ms, receive_ms, self._state_event(robot_id, version, msg, status, errors)
        )

    def _visualization(
        self, robot_id: str, version: str, msg: dict, sent_ms: int, receive_ms: int
    ) -> Envelope | Rejection:
        status = self.last_status.get(robot_id) or _Status(
            None, None, None, None, None, None, "", ""
        )
        event = self._state_event(robot_id, version, msg, status, ())
        if event.pose is not None:
            return make_envelope(robot_id, sent_ms, receive_ms, event.pose)
        if event.map_id is None:
            return Rejection(
                Reason.VDA_NO_POSITION,
                (
                    "a visualization without agvPosition (mobileRobotPosition) has nothing to "
                    "store; send it once the vehicle is localized"
                ),
            )
        return make_envelope(robot_id, sent_ms, receive_ms, event)  # stored, flagged

    def _state_event(
        self, robot_id: str, version: str, msg: dict, status: _Status, errors: tuple[VdaError, ...]
    ) -> VdaStateReported:
        position = msg.get("agvPosition") or msg.get("mobileRobotPosition")
        pose = map_id = x = y = theta = None
        known = False
        if position is not None:
            map_id, x, y, theta = position["mapId"], position["x"], position["y"], position["theta"]
            transform = self.transform_for(map_id)
            known = transform is not None
            localized = position.get("positionInitialized", position.get("localized", True))
            if transform is not None and localized:
                mx, my, mtheta = apply_transform(transform, x, y, theta)
                pose = PoseReported(
                    (mx, my, 0.0),
                    quaternion_z(mtheta),
                    status.battery,
                    status.charging,
                    status.loaded,
                    status.path,
                )
        return VdaStateReported(
            msg["manufacturer"],
            msg["serialNumber"],
            version,
            pose,
            map_id,
            known,
            x,
            y,
            theta,
            status.driving,
            status.paused,
            status.operating_mode,
            status.order_id,
            errors,
        )

    def transform_for(self, map_id: str) -> Transform | None:
        """The map id's transform into the map's frame: identity while none is configured;
        once some are, an unlisted map id is unknown (None)."""
        if not self.map_transforms:
            return (0.0, 0.0, 0.0)
        return self.map_transforms.get(map_id)

    def _path(self, msg: dict) -> tuple[tuple[float, float], ...] | None:
        """The positions still to drive: 3.0's plannedPath control points, else the order's
        remaining node positions (nodeStates lists only the nodes still to traverse)."""
        planned = msg.get("plannedPath")
        if planned:
            points = [(p["x"], p["y"], None) for p in planned["trajectory"]["controlPoints"]]
        else:
            points = [
                (n["nodePosition"]["x"], n["nodePosition"]["y"], n["nodePosition"]["mapId"])
                for n in msg.get("nodeStates", ())
                if "nodePosition" in n
            ]
        path = []
        for x, y, map_id in points:
            transform = (
                self.transform_for(map_id)
                if map_id is not None
                else (self.transform_for((msg.get("mobileRobotPosition") or {}).get("mapId", "")))
            )
            if transform is None:
                continue  # not drawn on a map it is not on
            mx, my, _ = apply_transform(transform, x, y, 0.0)
            path.append((mx, my))
        return tuple(path) if path else None


def apply_transform(
    transform: Transform, x: float, y: float, theta: float
) -> tuple[float, float, float]:
    dx, dy, rotation = transform
    c, s = math.cos(rotation), math.sin(rotation)
    return c * x - s * y + dx, s * x + c * y + dy, theta + rotation


def quaternion_z(theta: float) -> tuple[float, float, float, float]:
    """The quaternion (x, y, z, w) of a rotation by theta about the z axis."""
    return (0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2))
