"""How the simulator learns the zones: a listing that does not show the advertised edit yet
is read again, each new set of zones is taken once, a failed read keeps the known zones."""

from __future__ import annotations

import json
import time

import httpx

from mapservice.core.annotations import Zone
from mapservice.robot import zone_feed
from mapservice.robot.zone_feed import ZoneFeed, shows

ZONE = Zone(name="k", kind="keep_out", polygon=((0.0, 0.0), (1.0, 0.0), (1.0, 1.0)))


class Listings:
    """The API's answers in turn (the last repeated); an exception is raised."""

    def __init__(self, *answers) -> None:
        self.answers, self.calls = list(answers), 0

    def __call__(self):
        answer = self.answers[min(self.calls, len(self.answers) - 1)]
        self.calls += 1
        if isinstance(answer, Exception):
            raise answer
        return answer


def test_shows_the_advertised_edit() -> None:
    assert shows([("a", ZONE)], {"annotationId": "a", "change": "created"})
    assert not shows([], {"annotationId": "a", "change": "changed"})
    assert shows([], {"annotationId": "a", "change": "removed"})
    assert not shows([("a", ZONE)], {"annotationId": "a", "change": "removed"})


def test_a_stale_listing_is_read_again_until_it_shows_the_advertised_zone(monkeypatch) -> None:
    monkeypatch.setattr(zone_feed, "STALE_WAIT_S", 0.01)
    listings = Listings([], [], [("a", ZONE)])
    feed = ZoneFeed("http://unused", None, fetch=listings)
    assert feed.refresh() and feed.take() == [] and feed.take() is None
    feed.advertised(json.dumps({"annotationId": "a", "change": "created"}).encode())
    assert feed.refresh()
    assert listings.calls == 3 and feed.take() == [("a", ZONE)]
    assert feed.refresh() and feed.take() is None  # the same zones: nothing new to take


def test_a_failed_read_keeps_the_known_zones_and_a_garbled_advertisement_still_reads() -> None:
    listings = Listings([("a", ZONE)], httpx.ConnectError("refused"), [])
    feed = ZoneFeed("http://unused", None, fetch=listings)
    assert feed.refresh() and feed.take() == [("a", ZONE)]
    assert not feed.refresh() and feed.take() is None and feed.failures == 1
    feed.advertised(b"\xff not json")
    assert feed.refresh() and feed.take() == []


def test_the_thread_reads_on_an_advertisement_without_waiting_for_the_resync() -> None:
    listings = Listings([], [("a", ZONE)])
    feed = ZoneFeed("http://unused", None, resync_s=3600, fetch=listings)
    feed.refresh()
    feed.take()
    feed.start()
    try:
        feed.advertised(json.dumps({"annotationId": "a", "change": "created"}).encode())
        deadline = time.monotonic() + 10
        got = None
        while got is None and time.monotonic() < deadline:
            got = feed.take()
            time.sleep(0.02)
        assert got == [("a", ZONE)]
    finally:
        feed.stop()
