"""The advertisements the live views send robots (chunk changes, zone edits) and the
incident alerts (incident_alerts.py), encoded and published on one thread of their own:
encoding one (base64 + PNG) takes ~2 ms, which stays off the event loop and the store
thread, and each chunk's advertisements keep their order. Best effort: a
failure is logged, a backlog beyond its bound is dropped and counted."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Protocol

import structlog
from prometheus_client import Counter

from mapservice.core.events import Envelope
from mapservice.core.liveview import advertisement

log = structlog.get_logger(__name__)

ADS_DROPPED = Counter(
    "mapservice_advertisements_dropped_total",
    "Advertisements dropped because too many were waiting to be encoded",
)
MAX_PENDING_ADS = 10_000


class Advertiser(Protocol):
    def start(self) -> None: ...

    def publish(self, payload: dict[str, Any]) -> bool: ...

    def publish_to(self, topic: str, payload: dict[str, Any], retain: bool = False) -> bool: ...

    def stop(self) -> None: ...


class AdvertisementQueue:
    """Hands advertisements to `advertiser` on the queue's thread; never waits for them."""

    def __init__(self, advertiser: Advertiser, public_base_url: str) -> None:
        self.advertiser = advertiser
        self.public_base_url = public_base_url
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="advertiser")
        self._pending = 0
        self._pending_lock = threading.Lock()

    def chunk_changed(self, e: Envelope) -> None:
        """A change of the latest map; dropped (counted) when the backlog is full."""
        with self._pending_lock:
            if self._pending >= MAX_PENDING_ADS:
                ADS_DROPPED.inc()
                return
            self._pending += 1
        self._thread.submit(self._publish, e)

    def to_topic(self, topic: str, ad: dict[str, Any], retain: bool = False) -> None:
        """A document for `topic` (a zone edit's advertisement, an incident alert); dropped
        (counted) when the backlog is full."""
        with self._pending_lock:
            if self._pending >= MAX_PENDING_ADS:
                ADS_DROPPED.inc()
                return
            self._pending += 1
        self._thread.submit(self._publish_to, topic, ad, retain)

    def _publish(self, e: Envelope) -> None:
        try:
            self.advertiser.publish(advertisement(e, self.public_base_url))
        except Exception as exc:  # advertising is best effort; the history is not at stake
            log.warning("advertisement failed", error=str(exc))
        finally:
            with self._pending_lock:
                self._pending -= 1

    def _publish_to(self, topic: str, ad: dict[str, Any], retain: bool) -> None:
        try:
            if retain:
                self.advertiser.publish_to(topic, ad, retain=True)
            else:
                self.advertiser.publish_to(topic, ad)
        except Exception as exc:  # best effort, as chunk advertisements
            log.warning("advertisement failed", error=str(exc), topic=topic)
        finally:
            with self._pending_lock:
                self._pending -= 1

    def flush(self) -> None:
        """Waits until every advertisement handed over so far was published (tests)."""
        self._thread.submit(lambda: None).result()

    def close(self) -> None:
        self._thread.shutdown(wait=True)
