"""One intake for every 2019 write: a bad message is refused with the same reason whichever
channel brings it - MQTT (the gateway's ingestor), the 2019 REST API, `up`'s start-up map
upload (straight to Kafka) and `mapservice map upload` (the CLI, over REST).

The bad inputs come from one table of classes; each class generates several messages
(seeded), and each message goes through every channel that takes its kind (MQTT has no
meta topic: a meta.json goes through the other three)."""

from __future__ import annotations

import base64
import json
import random
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import msgspec
import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.api.app import create_app
from mapservice.core.events import MapMetaSet, make_envelope
from mapservice.core.intake import split_refusal
from mapservice.core.wire2019 import Reason, format_timestamp
from mapservice.ingest.gateway import Ingestor
from mapservice.robot.map_upload import MapMessages, UploadRefused, post_map, publish_map
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.conftest import NOW_MS

WRITER_TOKEN = "w" * 32
LIMIT: int = Settings.model_fields["max_message_bytes"].default
# The map every channel knows: stored in the service, applied by the gateway, the upload's own.
META = MapMetaSet(500, 400, 100, 100, 4, 5)
CASES_PER_CLASS = 4


def chunk_doc(rnd: random.Random, **overrides) -> dict:
    """A valid listing-10 chunk write of META's grid at now (random cell and pixels)."""
    doc = {
        "pgmB64compressedData": base64.b64encode(zlib.compress(rnd.randbytes(10_000))).decode(),
        "row": rnd.randrange(META.chunk_rows),
        "column": rnd.randrange(META.chunk_cols),
        "timestamp": format_timestamp(NOW_MS - rnd.randrange(60_000)),
        "robotId": rnd.choice(["lkjlkj", "map-upload", "r1"]),
    }
    return {**doc, **overrides}


def meta_doc(**overrides) -> dict:
    return {**META.to_2019(), **overrides}


def encoded(doc: dict) -> bytes:
    return json.dumps(doc).encode()


def padded(doc: dict, rnd: random.Random) -> bytes:
    """The document, valid JSON still, grown past the message limit with whitespace (some
    past the API's body limit too)."""
    data = encoded(doc)
    return data[:-1] + b" " * rnd.randint(LIMIT + 1 - len(data), 5 * LIMIT) + b"}"


def truncated(data: bytes, rnd: random.Random) -> bytes:
    """A strict prefix of a JSON object: never JSON."""
    return data[: rnd.randrange(1, len(data))]


def not_base64(rnd: random.Random) -> str:
    text = list(base64.b64encode(zlib.compress(rnd.randbytes(10_000))).decode())
    text[rnd.randrange(len(text))] = rnd.choice("!*?# $%&")
    return "".join(text)


def not_zlib(rnd: random.Random) -> str:
    """A zlib stream cut short, or bytes that are no zlib stream at all."""
    stream = zlib.compress(rnd.randbytes(10_000))
    data = stream[: rnd.randrange(2, len(stream) - 4)] if rnd.random() < 0.5 else b"\x00" * 40
    return base64.b64encode(data).decode()


def wrong_size(rnd: random.Random) -> str:
    size = rnd.choice([0, 1, 9_999, 10_001, rnd.randrange(2, 40_000)])
    size += size == 10_000
    return base64.b64encode(zlib.compress(rnd.randbytes(size))).decode()


def outside(rnd: random.Random) -> dict:
    """A cell outside META's 4 x 5 grid: a row or column past it, or negative."""
    row, column = rnd.randrange(META.chunk_rows), rnd.randrange(META.chunk_cols)
    if rnd.random() < 0.5:
        row = rnd.choice([META.chunk_rows + rnd.randrange(1000), -1 - rnd.randrange(1000)])
    else:
        column = rnd.choice([META.chunk_cols + rnd.randrange(1000), -1 - rnd.randrange(1000)])
    return {"row": row, "column": column}


def without(doc: dict, rnd: random.Random, fields: list[str]) -> dict:
    gone = rnd.choice(fields)
    return {k: v for k, v in doc.items() if k != gone}


CHUNK_FIELDS = ["pgmB64compressedData", "row", "column", "timestamp", "robotId"]
META_FIELDS = ["width", "height", "CHUNK_WIDTH", "CHUNK_HEIGHT", "CHUNK_ROWS", "CHUNK_COLS"]


@dataclass(frozen=True)
class BadInput:
    kind: str  # "chunk" (a listing-10/14 chunk write) or "meta" (a meta.json)
    reason: Reason
    make: Callable[[random.Random], bytes]


BAD_INPUTS: dict[str, BadInput] = {
    "oversized chunk": BadInput("chunk", Reason.OVERSIZED, lambda r: padded(chunk_doc(r), r)),
    "chunk not JSON": BadInput(
        "chunk", Reason.NOT_JSON, lambda r: truncated(encoded(chunk_doc(r)), r)
    ),
    "chunk missing a field": BadInput(
        "chunk", Reason.MISSING_FIELD, lambda r: encoded(without(chunk_doc(r), r, CHUNK_FIELDS))
    ),
    "chunk field of a wrong type": BadInput(
        "chunk",
        Reason.WRONG_TYPE,
        lambda r: encoded(chunk_doc(r, **{r.choice(["row", "column"]): str(r.randrange(4))})),
    ),
    "chunk pixels not base64": BadInput(
        "chunk",
        Reason.BAD_BASE64,
        lambda r: encoded(chunk_doc(r, pgmB64compressedData=not_base64(r))),
    ),
    "chunk pixels not zlib": BadInput(
        "chunk", Reason.BAD_ZLIB, lambda r: encoded(chunk_doc(r, pgmB64compressedData=not_zlib(r)))
    ),
    "chunk of another size": BadInput(
        "chunk",
        Reason.WRONG_CHUNK_SIZE,
        lambda r: encoded(chunk_doc(r, pgmB64compressedData=wrong_size(r))),
    ),
    "chunk outside the map": BadInput(
        "chunk", Reason.OUT_OF_MAP, lambda r: encoded(chunk_doc(r, **outside(r)))
    ),
    "chunk of a bad robot id": BadInput(
        "chunk",
        Reason.BAD_ROBOT_ID,
        lambda r: encoded(chunk_doc(r, robotId=r.choice(["", "a b", "x" * 65, "r/1", "é"]))),
    ),
    "chunk of a bad timestamp": BadInput(
        "chunk",
        Reason.BAD_TIMESTAMP,
        lambda r: encoded(chunk_doc(r, timestamp=r.choice(["yesterday", "", "2026-13-01"]))),
    ),
    "chunk from the future": BadInput(
        "chunk",
        Reason.TIMESTAMP_IN_FUTURE,
        lambda r: encoded(
            chunk_doc(r, timestamp=format_timestamp(NOW_MS + 301_000 + r.randrange(10**9)))
        ),
    ),
    "oversized meta": BadInput("meta", Reason.OVERSIZED, lambda r: padded(meta_doc(), r)),
    "meta not JSON": BadInput("meta", Reason.NOT_JSON, lambda r: truncated(encoded(meta_doc()), r)),
    "meta missing a size": BadInput(
        "meta", Reason.MISSING_FIELD, lambda r: encoded(without(meta_doc(), r, META_FIELDS))
    ),
    "meta size of a wrong type": BadInput(
        "meta", Reason.WRONG_TYPE, lambda r: encoded(meta_doc(**{r.choice(META_FIELDS): "wide"}))
    ),
    "meta size out of range": BadInput(
        "meta",
        Reason.OUT_OF_RANGE,
        lambda r: encoded(
            meta_doc(**{r.choice(META_FIELDS): r.choice([0, -r.randrange(1, 99), 70_000])})
        ),
    ),
    "meta resolution out of range": BadInput(
        "meta",
        Reason.OUT_OF_RANGE,
        lambda r: encoded(meta_doc(resolution=r.choice([0, -r.random(), 1e6 + r.random()]))),
    ),
    "meta grid short of the map": BadInput(
        "meta",
        Reason.GRID_SHORT_OF_MAP,
        lambda r: encoded(
            meta_doc(**{r.choice(["CHUNK_ROWS", "CHUNK_COLS"]): r.randrange(1, 4)})
            if r.random() < 0.5
            else meta_doc(width=r.randrange(501, 65_535))
        ),
    ),
}


class Channels:
    """Every way a 2019 write enters the log, over in-memory twins at one clock; each
    `refuse_*` returns the reason the channel refused the message with (None: taken).
    A refusal changes no state, so the tests share one (an app takes a second to make)."""

    def __init__(self) -> None:
        self.settings = Settings(
            admin_token="a" * 32, api_writer_tokens=WRITER_TOKEN, api_allowed_hosts=["testserver"]
        )
        assert self.settings.max_message_bytes == LIMIT
        self.store = MemoryStore()
        self.store.append([make_envelope("api", NOW_MS - 60_000, NOW_MS - 60_000, META)])
        self.rest_log = MemoryPublisher()
        app = create_app(
            self.settings, self.store, {}, ManualClock(NOW_MS), publisher=self.rest_log
        )
        self.http = TestClient(
            app, raise_server_exceptions=False, headers={"Authorization": f"Bearer {WRITER_TOKEN}"}
        )
        self.mqtt_log = MemoryPublisher()
        self.ingestor = Ingestor(self.settings, self.mqtt_log, ManualClock(NOW_MS), "gw", 0)
        self.ingestor.apply_meta(META)

    def refuse_over_mqtt(self, kind: str, data: bytes) -> str | None:
        assert kind == "chunk", "MQTT has no meta topic"
        return self.ingestor.handle("iot/chunks/create", data, lambda: None).reason

    def refuse_over_rest(self, kind: str, data: bytes) -> str | None:
        path = "/api/chunk-service/chunks" if kind == "chunk" else "/api/chunk-service/meta"
        self.rest_log.poll()
        self.rest_log.records.clear()  # what earlier (good) writes published
        r = self.http.post(path, content=data, headers={"Content-Type": "application/json"})
        if r.status_code == 200:
            return None
        assert r.status_code in (400, 413), r.text
        refusal = split_refusal(r.json()["detail"])
        assert refusal is not None, r.text
        self.rest_log.poll()
        assert not self.rest_log.records, "a refused write was published"
        return refusal[0].value

    def _upload(self, kind: str, data: bytes) -> MapMessages:
        good_meta = msgspec.json.encode(META.to_2019())
        return MapMessages(good_meta, [data]) if kind == "chunk" else MapMessages(data, [])

    def refuse_over_up(self, kind: str, data: bytes) -> str | None:
        log = MemoryPublisher()
        try:
            publish_map(log, self.settings, self._upload(kind, data), NOW_MS)
        except UploadRefused as refused:
            assert not log.records and not log._pending, "a refused upload was published"
            return refused.reason
        return None

    def refuse_over_cli(self, kind: str, data: bytes) -> str | None:
        try:
            post_map(self.http, self._upload(kind, data))
        except UploadRefused as refused:
            return refused.reason
        return None


@pytest.fixture(scope="module")
def channels() -> Channels:
    return Channels()


CHANNELS = {
    "mqtt": (Channels.refuse_over_mqtt, {"chunk"}),
    "rest": (Channels.refuse_over_rest, {"chunk", "meta"}),
    "up": (Channels.refuse_over_up, {"chunk", "meta"}),
    "cli": (Channels.refuse_over_cli, {"chunk", "meta"}),
}


@pytest.mark.parametrize(
    "name, seed",
    [
        pytest.param(name, seed, id=f"{name}-{seed}")
        for name in BAD_INPUTS
        for seed in range(CASES_PER_CLASS)
    ],
)
def test_a_bad_write_is_refused_with_one_reason_on_every_channel(name, seed, channels) -> None:
    """The generated bad message is refused by every channel that takes its kind, each
    naming the class's reason; nothing refused reaches the log."""
    bad = BAD_INPUTS[name]
    data = bad.make(random.Random(f"{name}-{seed}"))
    got = {
        channel: refuse(channels, bad.kind, data)
        for channel, (refuse, kinds) in CHANNELS.items()
        if bad.kind in kinds
    }
    assert got == dict.fromkeys(got, bad.reason.value)


@pytest.mark.parametrize("kind", ["chunk", "meta"])
def test_a_good_write_is_taken_on_every_channel(kind, channels) -> None:
    """The table's messages differ from a good one only in what makes them bad: the good
    one passes every channel (so a refusal above is the class's, not the harness's)."""
    rnd = random.Random(kind)
    data = encoded(chunk_doc(rnd) if kind == "chunk" else meta_doc())
    got = {
        channel: refuse(channels, kind, data)
        for channel, (refuse, kinds) in CHANNELS.items()
        if kind in kinds
    }
    assert got == dict.fromkeys(got)
