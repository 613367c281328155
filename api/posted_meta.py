"""The map meta this API instance has just published, until the processors have stored it.

A 2019 robot POSTs its meta.json and then its chunks at once (A.1.1): the chunks are
validated against the meta it posted, not only against the one the store holds yet."""

from __future__ import annotations

import threading

from mapservice.core.events import MapMetaSet

# How long a published meta stands in for the stored one: the processors store it in
# well under a second; a minute covers a restart of theirs.
POSTED_META_GRACE_MS = 60_000


class PostedMeta:
    """The last meta this instance published and when (shared by its request threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._posted: tuple[int, MapMetaSet] | None = None

    def published(self, at_ms: int, meta: MapMetaSet) -> None:
        with self._lock:
            self._posted = (at_ms, meta)

    def for_validation(self, stored: MapMetaSet | None, now_ms: int) -> MapMetaSet | None:
        """The meta to validate a chunk against: the stored one, or the one published in
        the last POSTED_META_GRACE_MS when the store does not hold it yet."""
        with self._lock:
            posted = self._posted
        if posted is None or stored == posted[1] or now_ms - posted[0] > POSTED_META_GRACE_MS:
            return stored
        return posted[1]
