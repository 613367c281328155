"""How simulated robots learn the operators' zones: all of them from the service's API on
start, again after every zone advertisement, and every `resync_s` (an advertisement lost
while disconnected must not leave robots driving through a zone for the rest of the shift).

An advertisement (MQTT, `iot/zones/advertisement`) says which zone changed, how, when and
by whom, and where the keep-out and speed masks as of that edit are. The masks are pixels;
the simulator wants the polygons (it rasterises them onto its own grid with the robot's
radius), so it reads the zones standing now from GET /api/v1/annotations. The API answers
an edit at once only in the process that took it: a listing that does not show the
advertised edit yet is read again, a few times, a moment later.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any

import httpx
import structlog

from mapservice.core.annotations import Zone

from .api_client import api_client
from .zones import zones_from_listing

log = structlog.get_logger("sim.zones")

Zones = list[tuple[str, Zone]]
STALE_RETRIES = 10
STALE_WAIT_S = 0.5
RETRY_S = 5.0


def shows(zones: Zones, advert: dict[str, Any]) -> bool:
    """Whether a listing already holds the advertised edit: a removed zone is gone, a
    created or changed one is there."""
    annotation_id = advert.get("annotationId")
    present = any(zone_id == annotation_id for zone_id, _ in zones)
    return not present if advert.get("change") == "removed" else present


class ZoneFeed:
    """Fetches the zones when told to (`advertised`, the periodic resync); the simulator's
    loop `take`s each new set of zones once, between two steps."""

    def __init__(
        self,
        api_url: str,
        token: str | None,
        resync_s: float = 60.0,
        fetch: Callable[[], Zones] | None = None,
    ) -> None:
        self.api_url = api_url
        self.token = token
        self.resync_s = resync_s
        self._fetch = fetch or self.fetch_api
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._adverts: list[dict[str, Any]] = []
        self._new: Zones | None = None
        self._last: Zones | None = None
        self._thread: threading.Thread | None = None
        self.fetches = self.failures = 0

    def fetch_api(self) -> Zones:
        with api_client(self.api_url, self.token, timeout=10) as http:
            response = http.get("/api/v1/annotations")
            response.raise_for_status()
            return zones_from_listing(response.json())

    def refresh(self) -> bool:
        """Fetches the zones now (for the advertisements waiting, until the listing shows
        them); True when it got an answer. A set of zones unlike the last is kept for `take`."""
        with self._lock:
            adverts, self._adverts = self._adverts, []
        for attempt in range(STALE_RETRIES):
            try:
                zones = self._fetch()
            except (httpx.HTTPError, ValueError) as exc:
                self.failures += 1
                log.warning(
                    "cannot read the zones; robots keep the ones they know",
                    api=self.api_url,
                    error=str(exc)[:300],
                    fix="check that the service's API is up at --api and the token reads",
                )
                return False
            self.fetches += 1
            if all(shows(zones, ad) for ad in adverts) or attempt == STALE_RETRIES - 1:
                break
            self._stop.wait(STALE_WAIT_S)
        with self._lock:
            if zones != self._last:
                self._new = self._last = zones
        return True

    def advertised(self, payload: bytes | bytearray) -> None:
        """An MQTT message on the zone advertisement topic (paho's thread: never blocks)."""
        try:
            advert = json.loads(payload)
            if not isinstance(advert, dict):
                raise ValueError("not a JSON object")
        except ValueError as exc:
            log.warning(
                "zone advertisement not understood; reading the zones anyway", error=str(exc)
            )
            advert = {}
        with self._lock:
            if advert:
                self._adverts.append(advert)
        self._wake.set()

    def take(self) -> Zones | None:
        """The zones, once after each change; None when nothing changed since."""
        with self._lock:
            new, self._new = self._new, None
        return new

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="zone-feed", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ok, last = self._last is not None, time.monotonic()
        while not self._stop.is_set():
            # An advertisement wakes it at once; else the resync, or a retry within
            # seconds while the API has not answered yet.
            wait = self.resync_s if ok else RETRY_S
            self._wake.wait(max(0.0, last + wait - time.monotonic()))
            if self._stop.is_set():
                return
            self._wake.clear()
            ok, last = self.refresh(), time.monotonic()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=15)
