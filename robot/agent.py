"""`mapservice robot`: a robot agent that keeps its local map in sync with the service.

The 2019 start-up and sync sequence (section 5.2 of the 2019 documentation), over the 2019
REST and MQTT API (appendix A):

1. GET /api/chunk-service/meta. None stored: POST this robot's meta and all its chunks.
   Stored: download the whole map (GET /api/chunk-service/chunks?latest=true) into the
   local map file.
2. Every period: integrate chunks other robots changed (each downloaded through its
   chunkUrl); in a period without any, look for local changes of
   the map file and publish every chunk whose content hash changed and that changed by
   more than the threshold (the seed's idea I.5) on iot/chunks/create.
3. Every period: publish pose and status on iot/coordinates/{robotId}, from a simulated
   drive on the map or from JSON odometry on a local MQTT topic (the 2019 ROS bridge).

Changes of other robots: the 2019 agent read every change of the plant on
iot/chunks/advertisement (`advertisements="2019"`). By default the agent reads only the
advertisement areas around it (areas.py), following its pose; until its first pose it reads
every area of the map, so nothing is missed between the download and the first pose.
"""

from __future__ import annotations

import os
import queue
import signal
import sys
import threading
import time
import zlib
from pathlib import Path

import httpx
import msgspec
import numpy as np
import structlog
import yaml

from mapservice.adapters.ros_map import load_ros_map, write_pgm
from mapservice.core.areas import DEFAULT_AREA_MARGIN_M, AreaGrid
from mapservice.core.events import MapMetaSet
from mapservice.core.wire2019 import encode_chunk_create, encode_coordinates, format_timestamp

from .api_client import api_client, writer_token
from .areas import AreaFeed, areas_around, map_areas
from .chunks import meta_to_json
from .commands import CommandInbox, SimCommands, command_topic, refusals
from .connection import RobotMqtt, robot_mqtt_from_args
from .local_map import LocalMap, chunk_body, compatible, decode_chunk_doc
from .map_upload import stored_meta
from .pose_sources import OdometryPose, SimulatedPose

log = structlog.get_logger("robot")

ADVERTISEMENT_TOPIC = "iot/chunks/advertisement"
# areas: the advertisement areas around the robot; 2019: every change, on the 2019 topic.
ADVERTISEMENT_MODES = ("areas", "2019")
CHUNK_TOPIC = "iot/chunks/create"
META_PATH = "/api/chunk-service/meta"
CHUNKS_PATH = "/api/chunk-service/chunks"


class RobotAgent:
    def __init__(
        self,
        map_yaml: str | Path,
        robot_id: str,
        api_url: str,
        mqtt_url: str,
        *,
        pose_source=None,
        threshold: float = 0.0,
        period_s: float = 1.0,
        chunk_width: int = 100,
        chunk_height: int = 100,
        http: httpx.Client | None = None,
        token: str | None = None,
        mqtt_conn: RobotMqtt | None = None,
        advertisements: str = "areas",
        area_grid: AreaGrid = AreaGrid(),
        area_margin_m: float = DEFAULT_AREA_MARGIN_M,
    ) -> None:
        if advertisements not in ADVERTISEMENT_MODES:
            raise ValueError(
                f"advertisements: one of {ADVERTISEMENT_MODES}, not {advertisements!r}"
            )
        self.map_yaml = Path(map_yaml)
        self.ros_map = load_ros_map(self.map_yaml)
        doc = yaml.safe_load(self.map_yaml.read_text())
        self.image_path = (self.map_yaml.parent / doc["image"]).resolve()
        self.robot_id = robot_id
        self.mqtt_url = mqtt_url
        self.conn = mqtt_conn or RobotMqtt(mqtt_url)  # its own credential, if it has one
        self.conn.check([robot_id])
        self.threshold = threshold
        self.period_s = period_s
        self.local = LocalMap.of(self.ros_map, chunk_width, chunk_height)
        # The writer token is what a 2019 robot adds: its REST writes need it.
        self.http = http or api_client(api_url, token)
        self.pose_source = pose_source
        self.adverts: queue.Queue[bytes] = queue.Queue()
        # Operators' commands: the simulated pose source obeys them; another refuses them.
        self.inbox = CommandInbox([robot_id])
        if isinstance(pose_source, SimulatedPose):
            pose_source.commands = SimCommands(self.inbox)
        self.stats = {"published_chunks": 0, "integrated_chunks": 0, "poses": 0, "errors": 0}
        self._stop = threading.Event()
        self._file_sig = self._signature()
        self._pending = False  # the file changed and its chunks were not compared yet
        self.client = None
        self.advertisements = advertisements
        self.area_grid = area_grid
        self.area_margin_m = area_margin_m
        self.area_feed: AreaFeed | None = None

    # -- the map file

    def _signature(self) -> tuple[int, ...]:
        st = self.image_path.stat()
        return st.st_mtime_ns, st.st_size, st.st_ino, st.st_ctime_ns

    def _write_map(self) -> None:
        tmp = self.image_path.with_name(f".{self.image_path.name}.{os.getpid()}.tmp")
        write_pgm(
            tmp,
            self.local.pixels,
            magic=self.ros_map.magic,
            comment=self.ros_map.comment,
            maxval=self.ros_map.max_brightness,
        )
        os.replace(tmp, self.image_path)  # readers never see half a map
        self._file_sig = self._signature()

    def _read_map_pixels(self) -> np.ndarray | None:
        sig = self._signature()
        if sig == self._file_sig:
            return None
        try:
            pixels = load_ros_map(self.map_yaml).pixels
        except (OSError, ValueError) as exc:  # caught mid-write by another program
            log.warning("map file unreadable, retrying", error=str(exc))
            return None
        self._file_sig = sig
        if pixels.shape != self.local.pixels.shape:
            log.error("map file changed size; keeping the old one", shape=pixels.shape)
            return None
        return pixels

    # -- start-up (2019 sequence)

    def remote_meta(self) -> MapMetaSet | None:
        return stored_meta(self.http)

    def start(self) -> str:
        """Uploads the map or downloads it; returns which ("uploaded" / "downloaded")."""
        remote = self.remote_meta()
        if remote is None:
            self.http.post(META_PATH, json=meta_to_json(self.local.meta)).raise_for_status()
            now = time.time_ns() // 1_000_000
            for row, column in self.local.cells():
                body = chunk_body(row, column, self.local.chunk(row, column), self.robot_id, now)
                self.http.post(CHUNKS_PATH, json=body).raise_for_status()
            log.info(
                "uploaded map",
                robot=self.robot_id,
                chunks=self.local.meta.chunk_rows * self.local.meta.chunk_cols,
            )
            return "uploaded"
        if not compatible(self.local.meta, remote):
            raise RuntimeError(
                f"the service's map is {remote.width} x {remote.height} px in {remote.chunk_width}"
                f" x {remote.chunk_height} chunks, this robot's is {self.local.meta.width} x "
                f"{self.local.meta.height} in {self.local.meta.chunk_width} x "
                f"{self.local.meta.chunk_height}; use the same map"
            )
        self.download_map()
        return "downloaded"

    def download_map(self) -> int:
        page, skip, count = 1000, 0, 0
        while True:
            resp = self.http.get(
                CHUNKS_PATH,
                params={
                    "latest": "true",
                    "limit": page,
                    "skip": skip,
                    "type": "pgm_base64_compressed",
                },
            )
            resp.raise_for_status()
            docs = resp.json()
            for doc in docs:
                self.local.integrate(*decode_chunk_doc(doc))
            count += len(docs)
            if len(docs) < page:
                break
            skip += page
        self._write_map()
        log.info("downloaded map", robot=self.robot_id, chunks=count)
        return count

    # -- the loop

    def _on_connect(self, client, userdata, flags, reason, properties=None) -> None:
        whole_plant = [(ADVERTISEMENT_TOPIC, 1)] if self.advertisements == "2019" else []
        client.subscribe([*whole_plant, (command_topic(self.robot_id), 1)])

    def _on_message(self, client, userdata, msg) -> None:
        if msg.topic == command_topic(self.robot_id):
            self.inbox.on_message(client, userdata, msg)
        else:
            self.adverts.put(msg.payload)

    def answer_commands(self) -> int:
        """Publishes the acks and outcomes of the commands taken since the last tick."""
        commands = getattr(self.pose_source, "commands", None)
        answers = (
            commands.drain()
            if commands is not None
            else refusals(
                self.inbox, "this robot's pose comes from its odometry; the agent cannot drive it"
            )
        )
        for answer in answers:
            self.client.publish(answer.topic, answer.payload, qos=1)
        return len(answers)

    def connect(self) -> None:
        self.client = self.conn.client(f"robot-{self.robot_id}", self.robot_id)
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        if self.advertisements == "areas":
            self.area_feed = AreaFeed(
                self.client, ADVERTISEMENT_TOPIC, lambda _c, _u, msg: self.adverts.put(msg.payload)
            )
            self.area_feed.move(self.robot_id, map_areas(self.local.meta, self.area_grid))
        self.conn.connect(self.client, who=f"robot {self.robot_id}")

    def follow(self, x: float, y: float) -> None:
        """Reads the advertisement areas around map point (x, y), and no other."""
        if self.area_feed is not None:
            self.area_feed.move(
                self.robot_id,
                areas_around(x, y, self.area_margin_m, self.local.meta, self.area_grid),
            )

    def _refresh_from_disk(self) -> None:
        """Takes up edits of the map file; they stay pending until compared and published."""
        pixels = self._read_map_pixels()
        if pixels is not None:
            self.local.pixels = pixels
            self._pending = True

    def integrate_adverts(self) -> int:
        """Downloads and writes every advertised chunk of another robot; how many changed.

        Local edits the file holds are read first, so writing the file keeps them (outside
        the advertised chunks) for the next local check."""
        if self.adverts.empty():
            return 0
        self._refresh_from_disk()
        changed = 0
        while True:
            try:
                raw = self.adverts.get_nowait()
            except queue.Empty:
                break
            try:
                advert = msgspec.json.decode(raw)
                if advert.get("robotId") == self.robot_id:
                    continue
                changed += self.local.integrate(*self._fetch_advertised(advert))
            except (
                msgspec.DecodeError,
                KeyError,
                TypeError,
                ValueError,
                AttributeError,
                zlib.error,
                httpx.HTTPError,
            ) as exc:
                self.stats["errors"] += 1
                log.warning("advertisement not integrated", error=str(exc))
        if changed:
            self._write_map()
            self.stats["integrated_chunks"] += changed
            log.info("integrated chunks of other robots", robot=self.robot_id, chunks=changed)
        return changed

    def _fetch_advertised(self, advert: dict) -> tuple[int, int, bytes]:
        """The advertised chunk, downloaded through its chunkUrl (A.1.3); the copy inside
        the advertisement only if the URL cannot be read (e.g. a wrong public_base_url)."""
        try:
            resp = self.http.get(advert["chunkUrl"])
            resp.raise_for_status()
            return decode_chunk_doc(resp.json())
        except httpx.HTTPError:
            if "chunk" not in advert:
                raise
            log.warning(
                "chunkUrl unreadable; using the advertisement's copy", url=advert["chunkUrl"]
            )
            return decode_chunk_doc(advert)

    def publish_local_changes(self) -> int:
        self._refresh_from_disk()
        if not self._pending:
            return 0
        self._pending = False
        now = time.time_ns() // 1_000_000
        changes = self.local.changes(self.local.pixels, self.threshold)
        for row, column, data in changes:
            self.client.publish(
                self.conn.chunk_topic(self.robot_id),
                encode_chunk_create(row, column, data, format_timestamp(now), self.robot_id),
                qos=1,
            )
        if changes:
            self.stats["published_chunks"] += len(changes)
            log.info("published local changes", robot=self.robot_id, chunks=len(changes))
        return len(changes)

    def publish_pose(self) -> bool:
        reading = self.pose_source.read() if self.pose_source is not None else None
        if reading is None:
            return False
        self.follow(reading.x, reading.y)
        now = time.time_ns() // 1_000_000
        self.client.publish(
            f"iot/coordinates/{self.robot_id}",
            encode_coordinates(
                self.robot_id,
                format_timestamp(now),
                reading.x,
                reading.y,
                reading.yaw_q,
                battery_level=reading.battery,
                charging=reading.charging,
                loaded=reading.loaded,
                path=list(reading.path) if reading.path else None,
            ),
            qos=1,
        )
        self.stats["poses"] += 1
        return True

    def tick(self) -> None:
        # 2019: an iteration that integrated external chunks skips the local check.
        if not self.integrate_adverts():
            self.publish_local_changes()
        self.publish_pose()
        self.answer_commands()

    def stop(self) -> None:
        self._stop.set()

    def run(self, seconds: float | None = None) -> None:
        self.connect()
        started = time.monotonic()
        try:
            while not self._stop.is_set():
                if seconds is not None and time.monotonic() - started >= seconds:
                    break
                began = time.monotonic()
                self.tick()
                self._stop.wait(max(0.0, self.period_s - (time.monotonic() - began)))
        finally:
            self.client.loop_stop()
            self.client.disconnect()


def main(args) -> None:
    from mapservice.runtime.logs import configure

    configure("INFO", "console", "robot")
    source = None
    try:
        ros_map = load_ros_map(args.map)
        if args.pose == "odom":
            source = OdometryPose(args.odom_mqtt or args.mqtt, args.odom_topic)
        else:
            source = SimulatedPose(ros_map, args.robot_id)
        agent = RobotAgent(
            args.map,
            args.robot_id,
            args.api,
            args.mqtt,
            pose_source=source,
            threshold=args.threshold,
            period_s=args.period,
            chunk_width=args.chunk_width,
            chunk_height=args.chunk_height,
            token=writer_token(args.token),
            mqtt_conn=robot_mqtt_from_args(args, args.mqtt),
            advertisements=args.advertisements,
            area_grid=AreaGrid(args.area_chunks),
            area_margin_m=args.area_margin,
        )
        signal.signal(signal.SIGTERM, lambda *_: agent.stop())
        how = agent.start()
        log.info("robot started", robot=args.robot_id, map=how, api=args.api, mqtt=args.mqtt)
        agent.run(args.seconds)
    except KeyboardInterrupt:
        pass
    except (OSError, ValueError, RuntimeError, httpx.HTTPError) as exc:
        sys.exit(f"mapservice robot: {exc}")
    finally:
        if isinstance(source, OdometryPose):
            source.close()
