"""Publishing a whole ROS map as events: its meta and every chunk (the 2019 `fillDB`).

Two routes, one meaning:
- `upload_map_events` writes `map.meta_set` and `chunk.updated` envelopes straight to Kafka
  with the same publisher the gateway and the REST API use (`mapservice up` on a fresh
  data dir);
- `upload_map_rest` posts them to a running service's 2019 REST API
  (`mapservice map upload`), which turns them into the same events.
Both refuse to overwrite a stored map of another size unless told to replace it.
"""

from __future__ import annotations

import base64
import zlib
from pathlib import Path

import httpx
import structlog

from mapservice.adapters.ros_map import RosMap, meta_for, slice_chunks

# UPLOADER_ID: the robot id the uploaded chunks are attributed to; the conflict rule and the
# change feed know its writes as a map upload.
from mapservice.core.change_feed import UPLOADER_ID
from mapservice.core.events import ChunkUpdated, MapMetaSet, encode, kafka_key, make_envelope
from mapservice.core.ports import EventPublisher
from mapservice.core.wire2019 import content_hash, format_timestamp
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


def upload_map_events(
    settings: Settings, ros_map: RosMap, now_ms: int, robot_id: str = UPLOADER_ID
) -> int:
    """Publishes the map's meta and all its chunks to Kafka; returns the chunk count."""
    from mapservice.adapters.kafka_publisher import KafkaPublisher

    meta = meta_for(ros_map)
    publisher = KafkaPublisher(settings, client_id="mapservice-map-upload")
    try:
        return _publish_map(publisher, settings, ros_map, meta, now_ms, robot_id)
    finally:
        # A producer left open keeps its threads and goes on dialling the broker for as
        # long as `up` runs (and logs refused connections once the broker stops).
        publisher.close()


def _publish_map(
    publisher: EventPublisher,
    settings: Settings,
    ros_map: RosMap,
    meta: MapMetaSet,
    now_ms: int,
    robot_id: str,
) -> int:
    errors: list = []
    meta_env = make_envelope(robot_id, now_ms, now_ms, meta)
    publisher.publish(
        settings.topic_meta_events, kafka_key(meta_env), encode(meta_env), errors.append
    )
    chunks = slice_chunks(ros_map, meta.chunk_width, meta.chunk_height)
    for (row, column), pixels in chunks.items():
        env = make_envelope(
            robot_id,
            now_ms,
            now_ms,
            ChunkUpdated(
                row,
                column,
                meta.chunk_width,
                meta.chunk_height,
                zlib.compress(pixels),
                content_hash(pixels),
            ),
        )
        publisher.publish(settings.topic_chunk_events, kafka_key(env), encode(env), errors.append)
    if publisher.flush(60) or any(errors):
        raise RuntimeError(f"could not publish the map to Kafka: {[e for e in errors if e]}")
    return len(chunks)


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
    Raises MapSizeMismatch when the stored map has another size and `replace` is not set."""
    from mapservice.robot.chunks import meta_to_json

    meta = meta_for(ros_map)
    stored = stored_meta(http)
    if stored is not None and not same_geometry(stored, meta) and not replace:
        raise MapSizeMismatch(
            mismatch_message(stored, meta, "this map")
            + "; --replace (admin) replaces the service's map"
        )
    if stored is None or not same_geometry(stored, meta):
        http.post("/api/chunk-service/meta", json=meta_to_json(meta)).raise_for_status()
    chunks = slice_chunks(ros_map, meta.chunk_width, meta.chunk_height)
    stamp = format_timestamp(now_ms)
    for (row, column), pixels in chunks.items():
        body = {
            "row": row,
            "column": column,
            "robotId": robot_id,
            "timestamp": stamp,
            "pgmB64compressedData": base64.b64encode(zlib.compress(pixels)).decode(),
        }
        http.post("/api/chunk-service/chunks", json=body).raise_for_status()
    return len(chunks)
