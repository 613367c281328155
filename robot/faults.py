"""What the simulator sends: step outputs encoded as 2019 MQTT messages, with the faults
real fleets have (a robot clock that is off, messages that never arrive, bad input).

Pure: the same outputs, options and tick give the same messages.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import msgspec

from mapservice.core.wire2019 import (
    encode_chunk_create,
    encode_coordinates,
    encode_pixels,
    format_timestamp,
)

from .sim import ChunkOut, PoseOut, StepOut

CHUNK_TOPIC = "iot/chunks/create"


def coordinate_topic(robot_id: str) -> str:
    return f"iot/coordinates/{robot_id}"


def legacy_chunk_topic(_robot_id: str) -> str:
    """The 2019 chunk topic, the same for every robot."""
    return CHUNK_TOPIC


@dataclass(frozen=True)
class Faults:
    clock_skew_s: float = 0.0  # each robot's clock is off by a fixed amount in [-s, +s]
    loss: float = 0.0  # probability that a message is not sent at all
    bad_rate: float = 0.0  # probability that a message is replaced by invalid input


@dataclass(frozen=True)
class Message:
    topic: str
    payload: bytes
    kind: str  # pose, chunk or bad:<what the gateway should say>
    robot_id: str = ""  # who sends it (its connection, where robots have credentials)


def robot_skew_ms(robot_id: str, faults: Faults, seed: int = 0) -> int:
    if faults.clock_skew_s <= 0:
        return 0
    return int(random.Random(f"skew:{seed}:{robot_id}").uniform(-1, 1) * faults.clock_skew_s * 1000)


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    import math

    return (0.0, 0.0, round(math.sin(yaw / 2), 6), round(math.cos(yaw / 2), 6))


def encode_pose(p: PoseOut, skew_ms: int = 0) -> bytes:
    return encode_coordinates(
        p.robot_id,
        format_timestamp(p.t_ms + skew_ms),
        p.x,
        p.y,
        yaw_quaternion(p.yaw),
        battery_level=p.battery,
        charging=p.charging,
        loaded=p.loaded,
        path=list(p.path),
    )


def encode_chunk(c: ChunkOut, skew_ms: int = 0) -> bytes:
    return encode_chunk_create(
        c.row, c.column, c.pixels, format_timestamp(c.t_ms + skew_ms), c.robot_id
    )


def bad_message(
    rng: random.Random,
    robot_id: str,
    t_ms: int,
    pixels: int = 10_000,
    chunk_topic=legacy_chunk_topic,
) -> Message:
    """One invalid message of a random class the gateway must dead-letter."""
    ts = format_timestamp(t_ms)
    good_chunk = msgspec.json.decode(encode_chunk_create(0, 0, bytes(pixels), ts, robot_id))
    kind = rng.choice(
        [
            "not_json",
            "bad_base64",
            "wrong_chunk_size",
            "out_of_map",
            "bad_timestamp",
            "robot_id_mismatch",
            "missing_field",
        ]
    )
    if kind == "not_json":
        return Message(
            coordinate_topic(robot_id),
            b'{"robotId": "' + robot_id.encode(),
            "bad:not_json",
            robot_id,
        )
    if kind == "robot_id_mismatch":
        doc = msgspec.json.decode(encode_coordinates("someone-else", ts, 0.0, 0.0))
        return Message(
            coordinate_topic(robot_id), msgspec.json.encode(doc), "bad:robot_id_mismatch", robot_id
        )
    if kind == "bad_timestamp":
        doc = msgspec.json.decode(encode_coordinates(robot_id, "yesterday noon", 0.0, 0.0))
        return Message(
            coordinate_topic(robot_id), msgspec.json.encode(doc), "bad:bad_timestamp", robot_id
        )
    if kind == "missing_field":
        doc = msgspec.json.decode(encode_coordinates(robot_id, ts, 0.0, 0.0))
        del doc["pose"]
        return Message(
            coordinate_topic(robot_id), msgspec.json.encode(doc), "bad:missing_field", robot_id
        )
    if kind == "bad_base64":
        good_chunk["pgmB64compressedData"] = "not*base64!"
    elif kind == "wrong_chunk_size":
        good_chunk["pgmB64compressedData"] = encode_pixels(bytes(pixels // 2))
    elif kind == "out_of_map":
        good_chunk["row"] = 999_999
    return Message(chunk_topic(robot_id), msgspec.json.encode(good_chunk), f"bad:{kind}", robot_id)


def to_messages(
    out: StepOut,
    faults: Faults = Faults(),
    *,
    seed: int = 0,
    tick: int = 0,
    chunk_pixels: int = 10_000,
    chunk_topic=legacy_chunk_topic,
) -> tuple[list[Message], int]:
    """The MQTT messages of one step and how many were lost on purpose; `chunk_topic(robotId)`
    is where a robot's chunks go (the 2019 topic, or its own where the broker checks
    identities)."""
    rng = random.Random(f"faults:{seed}:{tick}")
    messages: list[Message] = []
    lost = 0
    items: list[PoseOut | ChunkOut] = [*out.chunks, *out.poses]
    for item in items:
        if faults.loss and rng.random() < faults.loss:
            lost += 1
            continue
        if faults.bad_rate and rng.random() < faults.bad_rate:
            messages.append(bad_message(rng, item.robot_id, item.t_ms, chunk_pixels, chunk_topic))
            continue
        skew = robot_skew_ms(item.robot_id, faults, seed)
        if isinstance(item, PoseOut):
            messages.append(
                Message(
                    coordinate_topic(item.robot_id), encode_pose(item, skew), "pose", item.robot_id
                )
            )
        else:
            messages.append(
                Message(
                    chunk_topic(item.robot_id), encode_chunk(item, skew), "chunk", item.robot_id
                )
            )
    return messages, lost
