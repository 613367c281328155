"""Publishing a whole map: `map upload` through the 2019 REST API (meta + every chunk as
events), the size check shared with `drive`, and the once-per-data-dir upload of `up`."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from mapservice.adapters.clock import ManualClock
from mapservice.adapters.ros_map import RosMap, load_ros_map, meta_for, slice_chunks
from mapservice.api.app import create_app
from mapservice.core.wire2019 import content_hash
from mapservice.robot.drive import check_map_size
from mapservice.robot.map_upload import (
    MARKER,
    UPLOADER_ID,
    MapSizeMismatch,
    upload_map_if_fresh,
    upload_map_rest,
)
from mapservice.settings import Settings
from mapservice.testing.memory_publisher import MemoryPublisher
from mapservice.testing.memory_store import MemoryStore
from tests.fixtures.legacy import process
from tests.fixtures.paths import MAPS

NOW = 1_795_255_200_000
ADMIN_TOKEN, WRITER_TOKEN = "a" * 32, "w" * 32


@pytest.fixture
def service():
    """A service and a client holding a writer token, as `map upload` sends it."""
    store, publisher = MemoryStore(), MemoryPublisher()
    settings = Settings(admin_token=ADMIN_TOKEN, api_writer_tokens=WRITER_TOKEN)
    app = create_app(settings, store, {}, ManualClock(NOW), publisher=publisher)
    return (
        store,
        publisher,
        TestClient(
            app, raise_server_exceptions=False, headers={"Authorization": f"Bearer {WRITER_TOKEN}"}
        ),
    )


def test_upload_stores_meta_and_every_chunk_as_the_map_file(service) -> None:
    """On an empty service, the map at now is the sliced map file, chunk by chunk, written by
    robot `map-upload`."""
    store, publisher, http = service
    depot = load_ros_map(MAPS / "depot.yaml")
    count = upload_map_rest(http, depot, NOW - 1000)
    process(publisher, store)
    expected = {k: content_hash(px).hex() for k, px in slice_chunks(depot).items()}
    assert count == len(expected)
    got = {(c.row, c.column): c.content_hash for c in store.map_at(NOW)}
    assert got == expected
    assert {c.robot_id for c in store.map_at(NOW)} == {UPLOADER_ID}
    assert store.latest_meta().width == depot.width


def test_upload_of_another_size_is_refused_and_publishes_nothing(service) -> None:
    """A map whose size differs from the stored meta is refused with both sizes named; with
    replace the service still wants the admin token, and with it the map is replaced."""
    store, publisher, http = service
    upload_map_rest(http, load_ros_map(MAPS / "depot.yaml"), NOW - 2000)
    process(publisher, store)
    sandbox = load_ros_map(MAPS / "tb3_sandbox.yaml")
    with pytest.raises(MapSizeMismatch, match=r"604 x 307 px.*384 x 384 px"):
        upload_map_rest(http, sandbox, NOW - 1000)
    assert process(publisher, store) == 0
    with pytest.raises(httpx.HTTPStatusError) as refused:  # the service wants the admin token
        upload_map_rest(http, sandbox, NOW - 1000, replace=True)
    assert refused.value.response.status_code == 403
    http.headers["Authorization"] = f"Bearer {ADMIN_TOKEN}"
    upload_map_rest(http, sandbox, NOW - 1000, replace=True)
    process(publisher, store)
    assert store.latest_meta().width == 384


def test_drive_refuses_a_map_of_another_size(service) -> None:
    """`drive`'s check raises a clear message when the service stores another map size, and
    passes for the same size or an empty service."""
    store, publisher, http = service
    depot = meta_for(load_ros_map(MAPS / "depot.yaml"))
    check_map_size("http://test", depot, http)  # nothing stored yet: any map is fine
    upload_map_rest(http, load_ros_map(MAPS / "depot.yaml"), NOW - 1000)
    process(publisher, store)
    check_map_size("http://test", depot, http)
    warehouse = meta_for(load_ros_map(MAPS / "warehouse.yaml"))
    with pytest.raises(ValueError, match=r"service's map is 604 x 307 px.*1006 x 1674"):
        check_map_size("http://test", warehouse, http)


def test_drive_exits_before_publishing_on_a_size_mismatch(monkeypatch, tmp_path) -> None:
    """`mapservice drive` against a service of another map size exits with the message and
    never connects to MQTT (it stores nothing)."""
    import mapservice.robot.drive as drive

    stored = meta_for(load_ros_map(MAPS / "warehouse.yaml"))
    monkeypatch.setattr("mapservice.robot.map_upload.stored_meta", lambda http: stored)
    monkeypatch.setattr(drive, "Publisher", lambda *a: pytest.fail("drive connected to MQTT"))
    from mapservice.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["drive", "--map", str(MAPS / "depot.yaml"), "--api", "http://127.0.0.1:9"])
    assert "1006 x 1674" in str(exc.value) and "604 x 307" in str(exc.value)


def test_up_uploads_once_per_data_dir(monkeypatch, tmp_path) -> None:
    """The first `up` on a data dir publishes the map; a resumed one does not (it would
    overwrite later changes), nor does one with history from before uploads, and a map of
    another size is refused."""
    calls = []
    monkeypatch.setattr(
        "mapservice.robot.map_upload.upload_map_events",
        lambda settings, ros_map, now_ms: calls.append(now_ms) or 7,
    )
    legacy = tmp_path / "legacy"
    depot0 = load_ros_map(MAPS / "depot.yaml")
    assert upload_map_if_fresh(Settings(), legacy, depot0, NOW, had_history=True) == 0
    assert calls == [] and (legacy / MARKER).exists()
    depot = load_ros_map(MAPS / "depot.yaml")
    assert upload_map_if_fresh(Settings(), tmp_path, depot, NOW) == 7
    assert (tmp_path / MARKER).exists()
    assert upload_map_if_fresh(Settings(), tmp_path, depot, NOW + 1) == 0
    assert calls == [NOW]
    with pytest.raises(MapSizeMismatch, match=r"604 x 307 px map.*384 x 384.*--data-dir"):
        upload_map_if_fresh(Settings(), tmp_path, load_ros_map(MAPS / "tb3_sandbox.yaml"), NOW)


def test_upload_without_a_token_is_refused(service) -> None:
    """Without a writer token the service refuses the upload (401) and stores nothing."""
    store, publisher, http = service
    del http.headers["Authorization"]
    with pytest.raises(httpx.HTTPStatusError) as refused:
        upload_map_rest(http, load_ros_map(MAPS / "depot.yaml"), NOW - 1000)
    assert refused.value.response.status_code == 401
    assert process(publisher, store) == 0


def test_map_upload_cli_explains_what_to_do(monkeypatch, tmp_path) -> None:
    """`map upload --replace` without an admin token and an unreachable --api both exit with
    a message saying what to pass."""
    from mapservice.cli import main

    monkeypatch.delenv("MAPSERVICE_ADMIN_TOKEN", raising=False)
    monkeypatch.setenv("MAPSERVICE_DATA_DIR", str(tmp_path))  # no token `up` generated
    with pytest.raises(SystemExit, match="admin operation: pass --admin-token"):
        main(["map", "upload", str(MAPS / "depot.yaml"), "--replace"])
    with pytest.raises(SystemExit, match="is the service running"):
        main(["map", "upload", str(MAPS / "depot.yaml"), "--api", "http://127.0.0.1:9"])


def test_the_map_upload_to_kafka_releases_its_producer(monkeypatch) -> None:
    """`up`'s upload closes its Kafka producer once the map is published, and when publishing
    failed: a producer left open keeps dialling the broker for as long as `up` runs."""
    from mapservice.robot.map_upload import upload_map_events

    made: list[MemoryPublisher] = []

    def publisher(settings, client_id, fail_with=None):
        made.append(MemoryPublisher(fail_with=fail_with))
        return made[-1]

    monkeypatch.setattr("mapservice.adapters.kafka_publisher.KafkaPublisher", publisher)
    depot = load_ros_map(MAPS / "depot.yaml")
    assert upload_map_events(Settings(), depot, NOW) == len(slice_chunks(depot))
    assert made[-1].closed and made[-1].records

    monkeypatch.setattr(
        "mapservice.adapters.kafka_publisher.KafkaPublisher",
        lambda settings, client_id: publisher(settings, client_id, OSError("broker gone")),
    )
    with pytest.raises(RuntimeError, match="could not publish the map to Kafka"):
        upload_map_events(Settings(), depot, NOW)
    assert made[-1].closed


def noise_map(seed: int, width: int, height: int) -> RosMap:
    """A map of random pixels: its chunks barely compress."""
    pixels = np.random.default_rng(seed).integers(0, 256, (height, width), dtype=np.uint8)
    return RosMap(pixels=pixels, resolution=0.05, origin=(0.0, 0.0, 0.0))


@pytest.mark.parametrize("seed", range(3))
def test_up_refuses_a_map_the_intake_refuses_and_publishes_nothing(
    monkeypatch, tmp_path, seed
) -> None:
    """A map whose chunk writes exceed MAPSERVICE_MAX_MESSAGE_BYTES is refused by `up`'s
    check before anything starts and by its upload ('oversized', as the gateway would
    dead-letter them); nothing reaches Kafka and the data dir is not marked uploaded."""
    from mapservice.robot.map_upload import UploadRefused, check_map

    made: list[MemoryPublisher] = []
    monkeypatch.setattr(
        "mapservice.adapters.kafka_publisher.KafkaPublisher",
        lambda settings, client_id: made.append(MemoryPublisher()) or made[-1],
    )
    settings = Settings(max_message_bytes=1024 * (1 + seed))
    noisy = noise_map(seed, 150 + 50 * seed, 120)
    with pytest.raises(UploadRefused) as checked:
        check_map(settings, noisy, NOW)
    with pytest.raises(UploadRefused) as uploaded:
        upload_map_if_fresh(settings, tmp_path, noisy, NOW)
    assert checked.value.reason == uploaded.value.reason == "oversized"
    assert all(not p.records for p in made) and not (tmp_path / MARKER).exists()
    check_map(Settings(), noisy, NOW)  # within the default limit: taken


def test_map_upload_cli_names_the_refusal_reason(monkeypatch, tmp_path, service) -> None:
    """`mapservice map upload` of a map the service refuses exits naming the reason."""
    from mapservice.cli import main

    store, publisher, _ = service
    pgm = tmp_path / "noise.pgm"
    pixels = noise_map(0, 150, 120).pixels
    pgm.write_bytes(b"P5\n150 120\n255\n" + pixels.tobytes())
    (tmp_path / "noise.yaml").write_text(
        "image: noise.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"
        "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    small = create_app(
        Settings(admin_token=ADMIN_TOKEN, api_writer_tokens=WRITER_TOKEN, max_message_bytes=1024),
        store,
        {},
        ManualClock(NOW),
        publisher=publisher,
    )
    monkeypatch.setattr(
        "mapservice.robot.api_client.api_client",
        lambda api, token: TestClient(
            small, raise_server_exceptions=False, headers={"Authorization": f"Bearer {token}"}
        ),
    )
    with pytest.raises(SystemExit, match="the service refused the map: oversized: "):
        main(["map", "upload", str(tmp_path / "noise.yaml"), "--token", WRITER_TOKEN])
    assert process(publisher, store) == 1  # the meta; no chunk
