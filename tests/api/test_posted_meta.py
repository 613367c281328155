"""The meta an API instance has just published stands in for the stored one for a while."""

from __future__ import annotations

from mapservice.api.posted_meta import POSTED_META_GRACE_MS, PostedMeta
from mapservice.core.events import MapMetaSet


def _meta(width: int) -> MapMetaSet:
    return MapMetaSet(width, 200, 100, 100, width // 100, 2)


def test_the_stored_meta_until_one_is_published() -> None:
    assert PostedMeta().for_validation(None, 1_000) is None
    assert PostedMeta().for_validation(_meta(300), 1_000) == _meta(300)


def test_a_published_meta_stands_in_for_the_stored_one_only_within_its_grace() -> None:
    posted = PostedMeta()
    posted.published(1_000, _meta(400))
    for stored in (None, _meta(300)):
        assert posted.for_validation(stored, 1_000) == _meta(400)
        assert posted.for_validation(stored, 1_000 + POSTED_META_GRACE_MS) == _meta(400)
        assert posted.for_validation(stored, 1_001 + POSTED_META_GRACE_MS) == stored
    # Stored: the store's own, the same value.
    assert posted.for_validation(_meta(400), 1_000) == _meta(400)
