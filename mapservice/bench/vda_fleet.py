"""The VDA 5050 workload for `mapservice bench ingest --workload vda5050`: every vehicle a
`state` a second and a `visualization` five times a second (VDA 5050 2.0.0, schema-valid),
on `<interface>/v2/<manufacturer>/<serial>/...`, QoS 1.

Like RawFleet (bench/fleet/rawfleet.py) it is not the limit: pre-encoded PUBLISH packets
(`mqtt_packets.PublishTemplate`, only the timestamp and packet id filled in) written on a
few raw connections from one asyncio loop. A message counts as published when its PUBACK
arrived. A vehicle's state goes out with a visualization, stamped at least a millisecond
after it, so no two of its messages share a millisecond (a vehicle's pose is identified by
its robot id and event time) and no stamp runs ahead of its sending (the server times
publish -> stored from it).
"""

from __future__ import annotations

import asyncio
import json
import math
import threading
import time
from dataclasses import dataclass, field
from datetime import UTC, datetime
from urllib.parse import urlparse

from mapservice.bench.fleet.mqtt_packets import (
    DISCONNECT_PACKET,
    PacketReader,
    PublishTemplate,
    connect_packet,
)
from mapservice.core.vda_ids import robot_id_for

VISUALIZATION_PERIOD_S = 0.2
STATE_EVERY = 5  # visualizations per state: a state a second
MANUFACTURER = "VdaBench"
VERSION = "2.0.0"
_TS = "@@TS@@"
TICK_S = 0.01
ACK_WAIT_S = 30.0


def iso(ms: int) -> bytes:
    return (
        datetime.fromtimestamp(ms / 1000, UTC).strftime("%Y-%m-%dT%H:%M:%S.%f")[:-3] + "Z"
    ).encode()


def _header(serial: str) -> dict:
    return {
        "headerId": 1,
        "timestamp": _TS,
        "version": VERSION,
        "manufacturer": MANUFACTURER,
        "serialNumber": serial,
    }


def vehicle_messages(
    serial: str, index: int, centre: tuple[float, float], map_id: str = "floor"
) -> tuple[bytes, bytes]:
    """(visualization, state) payloads of one vehicle, the timestamp left as a marker."""
    angle = index * 0.7
    position = {
        "x": round(centre[0] + math.cos(angle), 3),
        "y": round(centre[1] + math.sin(angle), 3),
        "theta": round(angle, 3),
        "mapId": map_id,
        "positionInitialized": True,
    }
    visualization = {
        **_header(serial),
        "agvPosition": position,
        "velocity": {"vx": 0.5, "vy": 0.0, "omega": 0.0},
    }
    state = {
        **_header(serial),
        "orderId": f"order-{index}",
        "orderUpdateId": 0,
        "lastNodeId": "n0",
        "lastNodeSequenceId": 0,
        "driving": True,
        "operatingMode": "AUTOMATIC",
        "nodeStates": [],
        "edgeStates": [],
        "actionStates": [],
        "errors": [],
        "agvPosition": position,
        "loads": [{"loadId": f"L{index}"}] if index % 2 == 0 else [],
        "batteryState": {"batteryCharge": float(50 + index % 50), "charging": False},
        "safetyState": {"eStop": "NONE", "fieldViolation": False},
    }
    return (json.dumps(visualization).encode(), json.dumps(state).encode())


def _template(topic: str, payload: bytes) -> PublishTemplate:
    prefix, mark, suffix = payload.partition(_TS.encode())
    if not mark:
        raise ValueError("payload without the timestamp marker")
    return PublishTemplate(topic, prefix, suffix)


@dataclass
class VdaFleetStats:
    """As RawFleet's FleetStats: `published` holds (kind, robot id, event time ms, publish
    wall time) of every acknowledged message; VDA positions are poses."""

    poses: int = 0
    chunks: int = 0
    published: list[tuple[str, str, int, float]] = field(default_factory=list)
    report: dict = field(default_factory=dict)


class VdaFleet:
    """`vehicles` VDA 5050 vehicles on `connections` MQTT connections."""

    def __init__(
        self,
        mqtt_url: str,
        ros_map,
        vehicles: int,
        *,
        interface: str = "uagv",
        connections: int = 4,
        prefix: str = "v",
    ) -> None:
        url = urlparse(mqtt_url)
        self.host, self.port = url.hostname or "127.0.0.1", url.port or 1883
        width = ros_map.width * ros_map.resolution if ros_map is not None else 20.0
        height = ros_map.height * ros_map.resolution if ros_map is not None else 20.0
        ox, oy = (ros_map.origin[0], ros_map.origin[1]) if ros_map is not None else (0.0, 0.0)
        self.vehicles: list[tuple[str, PublishTemplate, PublishTemplate]] = []
        for i in range(vehicles):
            serial = f"{prefix}{i:05d}"
            centre = (
                ox + 1 + (i * 1.3) % max(width - 2, 1),
                oy + 1 + (i * 0.7) % max(height - 2, 1),
            )
            viz, state = vehicle_messages(serial, i, centre)
            base = f"{interface}/v2/{MANUFACTURER}/{serial}/"
            self.vehicles.append(
                (
                    robot_id_for(MANUFACTURER, serial),
                    _template(base + "visualization", viz),
                    _template(base + "state", state),
                )
            )
        self.connections = max(1, min(connections, vehicles))
        self.stats = VdaFleetStats()
        self._stop = threading.Event()

    # What each vehicle offers: five visualizations and a state a second.
    events_per_robot_s = (1 + 1 / STATE_EVERY) / VISUALIZATION_PERIOD_S

    def scheduled_events(self, seconds: float) -> int:
        """Messages the schedule asks for in `seconds` (whole visualization periods)."""
        slots = math.ceil(seconds / VISUALIZATION_PERIOD_S - 1e-9)
        per_vehicle = [
            slots + sum(1 for slot in range(slots) if (slot + k) % STATE_EVERY == 0)
            for group in range(self.connections)
            for k in range(len(self.vehicles[group :: self.connections]))
        ]
        return sum(per_vehicle)

    def stop(self) -> None:
        self._stop.set()

    def run(self, seconds: float | None = None) -> VdaFleetStats:
        asyncio.run(self._run(seconds))
        return self.stats

    async def _run(self, seconds: float | None) -> None:
        groups = [self.vehicles[i :: self.connections] for i in range(self.connections)]
        start = time.monotonic() + 0.5
        end = start + seconds if seconds is not None else math.inf
        late: list[float] = []
        await asyncio.gather(
            *(self._connection(n, group, start, end, late) for n, group in enumerate(groups))
        )
        late.sort()
        self.stats.report = {
            "vehicles": len(self.vehicles),
            "connections": self.connections,
            "lag_p99_s": late[int(0.99 * (len(late) - 1))] if late else None,
        }

    async def _connection(
        self, n: int, group: list, start: float, end: float, late: list[float]
    ) -> None:
        reader, writer = await asyncio.open_connection(self.host, self.port)
        writer.write(connect_packet(f"vda-bench-{n}-{time.monotonic_ns()}", 60, True))
        packets = PacketReader()
        pending: dict[int, tuple[str, int]] = {}
        next_pid = [0]

        async def read_acks() -> None:
            while True:
                data = await reader.read(65536)
                if not data:
                    return
                for pid in packets.feed(data):
                    entry = pending.pop(pid, None)
                    if entry is not None:
                        self.stats.poses += 1
                        self.stats.published.append(("pose", entry[0], entry[1], time.time()))

        acks = asyncio.create_task(read_acks())
        # Each vehicle's place in the 200 ms period, spread evenly over the group.
        offsets = [VISUALIZATION_PERIOD_S * i / max(len(group), 1) for i in range(len(group))]
        slot = 0  # visualization periods since start
        while not self._stop.is_set():
            period_start = start + slot * VISUALIZATION_PERIOD_S
            if period_start >= end:
                break
            for k, ((robot_id, viz, state), offset) in enumerate(zip(group, offsets)):
                due = period_start + offset
                delay = due - time.monotonic()
                if delay > TICK_S:
                    await writer.drain()
                    await asyncio.sleep(delay)
                late.append(max(0.0, time.monotonic() - due))
                sent_ms = self._send(writer, pending, next_pid, robot_id, viz)
                if (slot + k) % STATE_EVERY == 0:
                    # Its state, once a second, sent with the visualization and stamped at
                    # least a millisecond after it: the history keeps one pose per vehicle
                    # and millisecond, and the server times publish -> stored from the
                    # stamp, so no stamp may run ahead of its sending.
                    self._send(writer, pending, next_pid, robot_id, state, after_ms=sent_ms)
            slot += 1
            await writer.drain()
        deadline = time.monotonic() + ACK_WAIT_S
        while pending and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        writer.write(DISCONNECT_PACKET)
        await writer.drain()
        writer.close()
        acks.cancel()

    @staticmethod
    def _send(
        writer,
        pending: dict,
        next_pid: list[int],
        robot_id: str,
        template: PublishTemplate,
        after_ms: int | None = None,
    ) -> int:
        next_pid[0] = next_pid[0] % 65535 + 1
        while next_pid[0] in pending:  # 65,535 in flight on one connection: skip used ids
            next_pid[0] = next_pid[0] % 65535 + 1
        ms = time.time_ns() // 1_000_000
        if after_ms is not None:
            ms = max(ms, after_ms + 1)
        pending[next_pid[0]] = (robot_id, ms)
        writer.write(template.packet(next_pid[0], iso(ms)))
        return ms
