"""The processors are wired in one place (processors/composition.py): each part built once,
the views handed the store thread at construction, health asked of the parts themselves,
nothing pointing back. Composing does no I/O, so no broker is needed here."""

from __future__ import annotations

import asyncio
import time

import pytest

import mapservice.processors.composition as composition
from mapservice.processors.composition import compose_processors
from mapservice.settings import Settings
from mapservice.testing.memory_store import MemoryStore

PARTS = (
    "StoreThread",
    "KafkaLivePublisher",
    "HistorySink",
    "MqttAdvertiser",
    "LiveViews",
    "KafkaBatchSource",
    "HistoryConsumer",
    "WebhookDeliveries",
    "WebhookRegistrySync",
)


@pytest.fixture
def settings(tmp_path) -> Settings:
    return Settings(kafka_bootstrap="127.0.0.1:1", mqtt_url="mqtt://127.0.0.1:1", data_dir=tmp_path)


@pytest.fixture
def built(monkeypatch) -> dict[str, list]:
    """Every instance of each part the composition builds, by class name."""
    made: dict[str, list] = {name: [] for name in PARTS}
    for name in PARTS:
        cls = getattr(composition, name)

        def counted(*args, _cls=cls, _name=name, **kwargs):
            made[_name].append(part := _cls(*args, **kwargs))
            return part

        monkeypatch.setattr(composition, name, counted)
    return made


@pytest.fixture
def processors(settings, built):
    parts = compose_processors(settings, MemoryStore())
    yield parts
    parts.store_thread.close()


def test_each_part_is_built_once_and_handed_to_the_parts_that_use_it(processors, built) -> None:
    """One store thread, shared by the sink and the views (given at construction); the
    consumer holds the sink, the views and the source, whose assignments it hears."""
    assert {name: len(made) for name, made in built.items()} == dict.fromkeys(PARTS, 1)
    p = processors
    assert p.store_thread is built["StoreThread"][0]
    assert p.sink.thread is p.store_thread and p.views.store_thread is p.store_thread
    assert p.sink.live is p.live is built["KafkaLivePublisher"][0]
    assert p.views.advertiser is built["MqttAdvertiser"][0] and p.views.writer is p.sink.writer
    assert p.consumer.sink is p.sink and p.consumer.views is p.views
    source = built["KafkaBatchSource"][0]
    assert p.consumer.source is source and source.on_assigned == p.consumer.on_assigned
    # The incidents found reach the webhooks' deliveries, which the registry sync keeps
    # in step with the webhooks registered (through the store's registry role only).
    deliveries, sync = built["WebhookDeliveries"][0], built["WebhookRegistrySync"][0]
    assert p.webhooks is deliveries and p.views.incidents.alerts.webhooks is deliveries
    assert sync.deliveries is deliveries and sync.registry.role.__name__ == "WebhookRegistry"


def test_nothing_points_back_from_the_sink_or_the_views(processors) -> None:
    """The sink knows no consumer and the views no sink: health asks the consumer itself."""
    assert not hasattr(processors.sink, "consumer")
    assert not hasattr(processors.views, "sink")


def test_health_reports_the_consumer_and_the_inserts_as_they_are(processors) -> None:
    """Readiness follows the consumer's group membership and the inserts' state; liveness
    the consumer's heartbeat; the history status is the sink's."""
    p = processors
    ready, live = p.readiness(), p.liveness()
    assert set(ready) == {"processors", "history_consumer", "history_store"}
    assert set(live) == {"processors", "history_consumer"}
    assert ready["processors"]() and live["processors"]() and live["history_consumer"]()

    assert not ready["history_consumer"]()  # not yet in the consumer group
    p.consumer.source.on_assigned([])  # taken in as a standby, without partitions
    assert ready["history_consumer"]()

    assert ready["history_store"]() and p.history_status()["storing"]
    p.sink.health.failed(OSError("No space left on device"), "append_events")
    assert not ready["history_store"]()
    assert not p.history_status()["storing"] and "No space left" in p.history_status()["reason"]

    p.consumer.heartbeat.last = time.monotonic() - 10 * p.consumer.heartbeat.max_age_s
    assert not live["history_consumer"]()


def test_the_apps_shutdown_stops_the_views_advertiser(settings, built, monkeypatch) -> None:
    """The faust app's shutdown closes the views' advertisement thread and stops the
    advertiser the composition gave them."""
    stopped: list[str] = []
    p = compose_processors(settings, MemoryStore())
    advertiser = built["MqttAdvertiser"][0]
    monkeypatch.setattr(advertiser, "stop", lambda: stopped.append("advertiser"))
    monkeypatch.setattr(p.views, "close", lambda: stopped.append("views"))
    try:
        asyncio.run(p.app.on_before_shutdown.send())
    finally:
        p.store_thread.close()
    assert stopped == ["views", "advertiser"]


def test_the_webhooks_are_delivered_with_the_data_dirs_signing_key(settings, built) -> None:
    """Local mode: the signing key is generated once in the data dir and read back by the
    API and the processors alike, so both derive the same secrets; the deliveries take
    the delivery settings."""
    from mapservice.runtime.secrets import WEBHOOK_SIGNING_KEY_FILE, secrets_dir

    settings = settings.model_copy(update={"webhook_max_tries": 2, "webhook_timeout_s": 0.5})
    p = compose_processors(settings, MemoryStore())
    p.store_thread.close()
    key = (secrets_dir(settings.data_dir) / WEBHOOK_SIGNING_KEY_FILE).read_text().strip()
    assert len(key) >= 32 and built["WebhookRegistrySync"][0].signing_key == key
    assert p.webhooks.policy.max_tries == 2 and p.webhooks.policy.timeout_s == 0.5


def test_without_a_signing_key_no_webhook_is_delivered_to(settings, built) -> None:
    """Production without MAPSERVICE_WEBHOOK_SIGNING_KEY: the processors run without
    webhooks (the API refuses to register one, saying why)."""
    settings = settings.model_copy(update={"mode": "production"})
    p = compose_processors(settings, MemoryStore())
    p.store_thread.close()
    assert p.webhooks is None and p.views.incidents.alerts.webhooks is None
    assert built["WebhookDeliveries"] == [] and built["WebhookRegistrySync"] == []
