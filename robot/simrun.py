"""`mapservice sim`: runs the pure simulation in real time and publishes it over MQTT."""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import paho.mqtt.client as mqtt
import structlog

from mapservice.adapters.ros_map import RosMap
from mapservice.core.areas import DEFAULT_AREA_MARGIN_M, AreaGrid

from .areas import AreaFeed, areas_around_pixel
from .commands import CommandInbox, SimCommands
from .connection import RobotClients, RobotMqtt
from .faults import Faults, to_messages
from .sim import SimConfig, SimState, new_state, step, with_zones
from .zone_feed import ZoneFeed


@dataclass
class SimStats:
    robots: int = 0
    ticks: int = 0
    poses: int = 0
    chunks: int = 0
    bad: int = 0
    lost: int = 0
    errors: int = 0  # publishes the client or broker refused, disconnects
    map_changes: int = 0
    zone_changes: int = 0  # new sets of operators' zones the robots took on
    advertisements: int = 0  # map changes read on the areas' topics around the robots
    started: float = field(default_factory=time.monotonic)
    recent: deque = field(default_factory=lambda: deque(maxlen=5))
    window: deque = field(default_factory=lambda: deque(maxlen=20))  # (monotonic, sent so far)

    @property
    def sent(self) -> int:
        return self.poses + self.chunks + self.bad

    def rate(self) -> float:
        if len(self.window) < 2:
            return 0.0
        (t0, n0), (t1, n1) = self.window[0], self.window[-1]
        return (n1 - n0) / max(t1 - t0, 1e-9)


class SimRunner:
    def __init__(
        self,
        mqtt_url: str,
        ros_map: RosMap,
        robots: int,
        *,
        faults: Faults = Faults(),
        seed: int = 7,
        config: SimConfig = SimConfig(),
        prefix: str = "sim",
        qos: int = 1,
        mqtt_conn: RobotMqtt | None = None,
        zone_feed: ZoneFeed | None = None,
        zone_topic: str = "iot/zones/advertisement",
        advertisement_topic: str | None = None,
        area_grid: AreaGrid = AreaGrid(),
        area_margin_m: float = DEFAULT_AREA_MARGIN_M,
    ) -> None:
        self.mqtt_url = mqtt_url
        # Where robots have credentials, each connects as itself (RobotClients).
        self.conn = mqtt_conn or RobotMqtt(mqtt_url)
        self.faults = faults
        self.seed = seed
        self.qos = qos
        now_ms = time.time_ns() // 1_000_000
        self.state: SimState = new_state(
            ros_map, robots, seed=seed, t_ms=now_ms, config=config, prefix=prefix
        )
        hosted = len(self.state.robots)
        if hosted < robots:
            structlog.get_logger("sim").warning(
                "the map has room for fewer robots; running fewer",
                asked=robots,
                running=hosted,
                planning_cell_m=round(self.state.config.cell_m, 3),
            )
        self.stats = SimStats(robots=hosted)
        # Operators' commands, each robot's on its own topic, applied between ticks.
        self.commands = SimCommands(CommandInbox(r.robot_id for r in self.state.robots))
        self.conn.check([r.robot_id for r in self.state.robots])
        self.zone_feed = zone_feed
        self.zone_topic = zone_topic
        # None: the robots read no map changes; else each reads the areas around it.
        self.advertisement_topic = advertisement_topic
        self.area_grid = area_grid
        self.area_margin_px = area_margin_m / ros_map.resolution
        self.area_feeds: dict[str | None, AreaFeed] = {}
        self._stop = threading.Event()
        self._closing = False

    def stop(self) -> None:
        self._stop.set()

    def _on_disconnect(self, client, userdata, flags, reason, properties=None) -> None:
        if not self._stop.is_set() and not self._closing:
            self.stats.errors += 1
            structlog.get_logger("sim").warning(
                "disconnected from the MQTT broker", reason=str(reason)
            )

    def _listen_for_zones(self, clients: RobotClients) -> None:
        """Hands each zone advertisement to the feed; read on the first robot's own
        connection (or the shared anonymous one), as one more connection under a robot's
        credential would throw that robot's off the broker."""
        assert self.zone_feed is not None
        feed = self.zone_feed
        clients.subscribe(self.zone_topic, lambda _c, _u, msg: feed.advertised(msg.payload))

    def _read_areas(self, clients: RobotClients) -> None:
        """An area feed on each connection (each robot's own, or the shared one)."""

        def advertised(_c, _u, _msg) -> None:
            self.stats.advertisements += 1

        assert self.advertisement_topic is not None
        self.area_feeds = {
            key: AreaFeed(client, self.advertisement_topic, advertised)
            for key, client in clients.clients.items()
        }

    def follow_robots(self) -> None:
        """Each robot reads the areas around where it is now."""
        if not self.area_feeds:
            return
        meta, grid, margin = self.state.meta, self.area_grid, self.area_margin_px
        for robot in self.state.robots:
            feed = self.area_feeds[robot.robot_id if self.conn.authenticated else None]
            feed.move(robot.robot_id, areas_around_pixel(*robot.pos, margin, meta, grid))

    def apply_zones(self) -> None:
        """Takes on the zones the feed fetched since the last step, if any."""
        zones = self.zone_feed.take() if self.zone_feed is not None else None
        if zones is None:
            return
        self.state, notes = with_zones(self.state, zones)
        self.stats.zone_changes += 1
        self.stats.recent.extend(notes)
        structlog.get_logger("sim").info(
            "robots take on the operators' zones",
            zones=len(zones),
            keep_out=sum(z.kind == "keep_out" for _, z in zones),
            speed=sum(z.kind == "speed_limit" for _, z in zones),
            robots=notes,
        )

    def run(self, seconds: float | None = None, on_tick=None) -> SimStats:
        clients = RobotClients(
            self.conn,
            [r.robot_id for r in self.state.robots],
            f"sim-{self.seed}",
            on_disconnect=self._on_disconnect,
        )
        clients.connect()
        self.commands.inbox.attach_fleet(clients)
        if self.advertisement_topic is not None:
            self._read_areas(clients)
        if self.zone_feed is not None:
            self._listen_for_zones(clients)
            self.zone_feed.refresh()  # the zones standing before the first step
            self.apply_zones()
            self.zone_feed.start()
        started = time.monotonic()
        dt = self.state.config.dt_s
        chunk_px = self.state.meta.chunk_width * self.state.meta.chunk_height
        try:
            while not self._stop.is_set():
                if seconds is not None and time.monotonic() - started >= seconds:
                    break
                # Simulated time follows the wall clock, so timestamps are real ones.
                wait = self.state.t_ms / 1000 + dt - time.time()
                if wait > 0:
                    self._stop.wait(wait)
                    continue
                self.apply_zones()
                before = self.commands.before_step(self.state)
                self.state, out = self.commands.after_step(before, *step(before))
                self.follow_robots()
                messages, lost = to_messages(
                    out,
                    self.faults,
                    seed=self.seed,
                    tick=self.state.tick,
                    chunk_pixels=chunk_px,
                    chunk_topic=self.conn.chunk_topic,
                )
                s = self.stats
                s.ticks += 1
                s.lost += lost
                s.map_changes += len(out.notes)
                s.recent.extend(out.notes)
                for msg in messages:
                    info = clients.publish(msg.robot_id, msg.topic, msg.payload, qos=self.qos)
                    if info.rc != mqtt.MQTT_ERR_SUCCESS:
                        s.errors += 1
                    elif msg.kind == "pose":
                        s.poses += 1
                    elif msg.kind == "chunk":
                        s.chunks += 1
                    else:
                        s.bad += 1
                for answer in self.commands.drain():
                    if (
                        clients.publish(answer.robot_id, answer.topic, answer.payload).rc
                        != mqtt.MQTT_ERR_SUCCESS
                    ):
                        s.errors += 1
                s.window.append((time.monotonic(), s.sent))
                if on_tick is not None:
                    on_tick(self)
        finally:
            self._closing = True  # our own disconnects are no errors
            if self.zone_feed is not None:
                self.zone_feed.stop()
            clients.close()
        return self.stats


def progress_table(runner: SimRunner):
    """What `mapservice sim` shows while it runs."""
    from rich.table import Table

    s = runner.stats
    table = Table(title=f"mapservice sim -> {runner.mqtt_url}", show_header=False, min_width=60)
    table.add_row("robots", str(s.robots))
    table.add_row("rate", f"{s.rate():.1f} msg/s")
    table.add_row("sent", f"{s.poses} poses, {s.chunks} chunks, {s.bad} bad on purpose")
    table.add_row("lost on purpose", str(s.lost))
    table.add_row("errors", f"[red]{s.errors}[/red]" if s.errors else "0")
    robots = runner.state.robots
    tasks: dict[str, int] = {}
    for r in robots:
        tasks[r.task] = tasks.get(r.task, 0) + 1
    table.add_row("doing", ", ".join(f"{n} {t}" for t, n in sorted(tasks.items())))
    if robots:
        table.add_row(
            "battery",
            f"min {min(r.battery for r in robots):.0f} %, {sum(r.loaded for r in robots)} loaded",
        )
    table.add_row("map changes", f"{s.map_changes}" + (f": {s.recent[-1]}" if s.recent else ""))
    if runner.area_feeds:
        table.add_row(
            "changes read",
            f"{s.advertisements} advertisements of the areas around the robots",
        )
    if runner.zone_feed is not None:
        table.add_row(
            "operators' zones",
            f"{len(runner.state.zones.zones)} standing, {s.zone_changes} changes taken on",
        )
    return table
