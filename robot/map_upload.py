"""Publishing a whole ROS map as events: its meta and every chunk (the 2019 `fillDB`).

A map is uploaded as the 2019 writes a robot would send (`map_messages`: its meta.json and
one listing-10 chunk per chunk), by two routes with one meaning:
- `upload_map_events` passes them through the intake the gateway and the REST API use, then
  publishes the events to Kafka (`mapservice up` on a fresh data dir);
- `upload_map_rest` posts them to a running service's 2019 REST API
  (`mapservice map upload`), which passes them through that intake.
Either way a message the intake refuses stops the upload with `UploadRefused`, naming the
reason an MQTT dead letter would give. Both refuse to overwrite a stored map of another
size unless told to replace it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import httpx
import msgspec
import structlog

from mapservice.adapters.ros_map import RosMap, meta_for, slice_chunks

# UPLOADER_ID: the robot id the uploaded chunks are attributed to; the conflict rule and the
# change feed know its writes as a map upload.
from mapservice.core.change_feed import UPLOADER_ID
from mapservice.core.events import Envelope, MapMetaSet, encode, kafka_key, make_envelope
from mapservice.core.intake import Intake, split_refusal
from mapservice.core.ports import EventPublisher
from mapservice.core.wire2019 import Rejection, encode_chunk_create, format_timestamp
from mapservice.settings import Settings

log = structlog.get_logger(__name__)

MARKER = "map-uploaded"  # in the data dir: this data dir's map was uploaded once


class MapSizeMismatch(ValueError):
    """The service stores a map of another geometry than the one offered."""


def same_geometry(a: MapMetaSet, b: MapMetaSet) -> bool:
    return (a.width, a.height, a.chunk_width, a.chunk_height) == (
        b.width,
        b.height,
        b.chunk_width,
        b.chunk_height,
    )


def mismatch_message(stored: MapMetaSet, offered: MapMetaSet, what: str) -> str:
    return (
        f"the service's map is {stored.width} x {stored.height} px in {stored.chunk_width}"
        f" x {stored.chunk_height} chunks, {what} is {offered.width} x {offered.height} px"
        f" in {offered.chunk_width} x {offered.chunk_height}; use the service's map "
        "(GET /api/chunk-service/meta) or start the service with this one"
    )


class UploadRefused(ValueError):
    """The intake refused one of the map's messages; `reason` is its code, as an MQTT dead
    letter or a REST refusal names it."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(f"{reason}: {detail}")
        self.reason, self.detail = reason, detail

    @classmethod
    def of(cls, rejection: Rejection) -> UploadRefused:
        return cls(rejection.reason.value, rejection.detail)


@dataclass(frozen=True)
class MapMessages:
    """A map as the 2019 writes that upload it."""

    meta: bytes  # meta.json (listing 8, with the ROS resolution and origin)
    chunks: list[bytes]  # one chunk write (listing 10) per chunk


def map_messages(ros_map: RosMap, now_ms: int, robot_id: str = UPLOADER_ID) -> MapMessages:
    meta = meta_for(ros_map)
    stamp = format_timestamp(now_ms)
    return MapMessages(
        msgspec.json.encode(meta.to_2019()),
        [
            encode_chunk_create(row, column, pixels, stamp, robot_id)
            for (row, column), pixels in slice_chunks(
                ros_map, meta.chunk_width, meta.chunk_height
            ).items()
        ],
    )


def admitted_meta(intake: Intake, meta_json: bytes) -> MapMetaSet:
    """The meta the intake takes from `meta_json`; raises UploadRefused when it refuses it."""
    meta = intake.map_meta(meta_json)
    if isinstance(meta, Rejection):
        raise UploadRefused.of(meta)
    return meta


def admit_map(
    intake: Intake, messages: MapMessages, now_ms: int, robot_id: str = UPLOADER_ID
) -> list[Envelope]:
    """The map's events, each message through the intake (the chunks against the map's own
    meta); raises UploadRefused at the first message it refuses."""
    meta = admitted_meta(intake, messages.meta)
    chunk_intake = intake.with_meta(meta)
    envelopes = [make_envelope(robot_id, now_ms, now_ms, meta)]
    for message in messages.chunks:
        envelope = chunk_intake.chunk(message, now_ms)
        if isinstance(envelope, Rejection):
            raise UploadRefused.of(envelope)
        envelopes.append(envelope)
    return envelopes


def check_map(settings: Settings, ros_map: RosMap, now_ms: int) -> None:
    """Raises UploadRefused when the intake would refuse the map's upload (`up` asks before
    it starts anything)."""
    admit_map(Intake.from_settings(settings), map_messages(ros_map, now_ms), now_ms)


def upload_map_events(
    settings: Settings, ros_map: RosMap, now_ms: int, robot_id: str = UPLOADER_ID
) -> int:
    """Publishes the map's meta and all its chunks to Kafka; returns the chunk count."""
    from mapservice.adapters.kafka_publisher import KafkaPublisher

    messages = map_messages(ros_map, now_ms, robot_id)
    publisher = KafkaPublisher(settings, client_id="mapservice-map-upload")
    try:
        return publish_map(publisher, settings, messages, now_ms, robot_id)
    finally:
        # A producer left open keeps its threads and goes on dialling the broker for as
        # long as `up` runs (and logs refused connections once the broker stops).
        publisher.close()


def publish_map(
    publisher: EventPublisher,
    settings: Settings,
    messages: MapMessages,
    now_ms: int,
    robot_id: str = UPLOADER_ID,
) -> int:
    """Publishes the map's events once the intake took every message (nothing is published
    when it refuses one); returns the chunk count."""
    publish_events(
        publisher, settings, admit_map(Intake.from_settings(settings), messages, now_ms, robot_id)
    )
    return len(messages.chunks)


def publish_events(
    publisher: EventPublisher, settings: Settings, envelopes: list[Envelope], what: str = "the map"
) -> None:
    """Publishes a map's admitted events (its meta, its chunks) and waits until Kafka has
    them all; raises RuntimeError when it does not take one."""
    errors: list = []
    for envelope in envelopes:
        topic = (
            settings.topic_meta_events
            if isinstance(envelope.payload, MapMetaSet)
            else settings.topic_chunk_events
        )
        publisher.publish(topic, kafka_key(envelope), encode(envelope), errors.append)
    if publisher.flush(60) or any(errors):
        raise RuntimeError(f"could not publish {what} to Kafka: {[e for e in errors if e]}")


def check_data_dir_map(data_dir: Path, ros_map: RosMap) -> bool:
    """True when the data dir already had its map uploaded; raises MapSizeMismatch when that
    map has another size (checked before anything is published)."""
    marker = Path(data_dir) / MARKER
    if not marker.exists():
        return False
    stored = marker.read_text().split()[0]
    if stored != f"{ros_map.width}x{ros_map.height}":
        raise MapSizeMismatch(
            f"{data_dir} holds a {stored.replace('x', ' x ')} px map, this one is "
            f"{ros_map.width} x {ros_map.height} px; use another --data-dir for it"
        )
    return True


def upload_map_if_fresh(
    settings: Settings, data_dir: Path, ros_map: RosMap, now_ms: int, had_history: bool = False
) -> int:
    """On a data dir that never had its map uploaded, publishes it; returns the chunk count
    (0 when the data dir already had it: a resumed service keeps its later changes).
    Raises MapSizeMismatch when the data dir holds a map of another size. `had_history`:
    the data dir had ClickHouse data before this start (then nothing is uploaded)."""
    if check_data_dir_map(data_dir, ros_map):
        return 0
    marker = Path(data_dir) / MARKER
    marker.parent.mkdir(parents=True, exist_ok=True)
    if had_history:
        # A data dir from before uploads at start: its map is whatever robots wrote; an
        # upload now would overwrite their later changes.
        marker.write_text(f"{ros_map.width}x{ros_map.height} at {now_ms} (not uploaded)\n")
        log.info("data dir has history from before map uploads; not uploading the map")
        return 0
    count = upload_map_events(settings, ros_map, now_ms)
    marker.write_text(f"{ros_map.width}x{ros_map.height} at {now_ms}\n")
    log.info("uploaded the map", chunks=count, robot=UPLOADER_ID)
    return count


def stored_meta(http: httpx.Client) -> MapMetaSet | None:
    """The map meta the service stores, or None (2019 GET /api/chunk-service/meta)."""
    from mapservice.robot.chunks import meta_from_json

    resp = http.get("/api/chunk-service/meta")
    if resp.status_code == 404:
        return None
    resp.raise_for_status()
    doc = resp.json() if resp.content else None
    if not doc or "CHUNK_WIDTH" not in doc:
        return None
    return meta_from_json(doc)


def upload_map_rest(
    http: httpx.Client,
    ros_map: RosMap,
    now_ms: int,
    replace: bool = False,
    robot_id: str = UPLOADER_ID,
) -> int:
    """Posts the map's meta and chunks to the 2019 REST API; returns the chunk count.
    Raises MapSizeMismatch when the stored map has another size and `replace` is not set,
    UploadRefused when the service refuses one of the map's messages."""
    meta = meta_for(ros_map)
    stored = stored_meta(http)
    if stored is not None and not same_geometry(stored, meta) and not replace:
        raise MapSizeMismatch(
            mismatch_message(stored, meta, "this map")
            + "; --replace (admin) replaces the service's map"
        )
    messages = map_messages(ros_map, now_ms, robot_id)
    return post_map(http, messages, with_meta=stored is None or not same_geometry(stored, meta))


def post_map(http: httpx.Client, messages: MapMessages, with_meta: bool = True) -> int:
    """Posts the map's messages (its meta.json first when `with_meta`); returns the chunk
    count. A message the service refuses (400, 413) raises UploadRefused with its reason."""
    posts = [("/api/chunk-service/meta", messages.meta)] if with_meta else []
    posts += [("/api/chunk-service/chunks", chunk) for chunk in messages.chunks]
    for path, body in posts:
        resp = http.post(path, content=body, headers={"Content-Type": "application/json"})
        if resp.status_code in (400, 413):
            text = _detail(resp)
            refusal = split_refusal(text)
            if refusal is None:
                raise UploadRefused(f"http_{resp.status_code}", text)
            raise UploadRefused(refusal[0].value, refusal[1])
        resp.raise_for_status()
    return len(messages.chunks)


def _detail(resp: httpx.Response) -> str:
    try:
        detail = resp.json().get("detail")
    except ValueError:
        detail = None
    return detail if isinstance(detail, str) else resp.text[:500]
