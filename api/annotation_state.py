"""The annotations standing at an instant as this API process sees them: the store's,
with the edits this process published lately applied (the processors store an edit a
second or two after Kafka took it; the operator who made it sees it at once)."""

from __future__ import annotations

import threading

from mapservice.core.annotations import (
    AnnotationCreated,
    AnnotationEdit,
    CurrentAnnotation,
    fold_annotations,
)
from mapservice.core.ports import AnnotationReader

# How long this process answers from its own published edits besides the store's: well
# beyond the second or two the processors take to store them.
RECENT_MS = 60_000


class RecentEdits:
    """The edits this process published lately (read-your-writes before the store has them)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.edits: list[AnnotationEdit] = []
        self.last_ms = 0

    def stamp(self, now_ms: int, after_ms: int = 0) -> int:
        """The time of a new edit: now, but after this process's previous edit and after
        `after_ms` (the edited annotation's last change): edits of one annotation are
        ordered by time, and two in one millisecond would be ordered by their ids."""
        with self.lock:
            self.last_ms = max(now_ms, self.last_ms + 1, after_ms + 1)
            return self.last_ms

    def add(self, edit: AnnotationEdit) -> None:
        with self.lock:
            self.edits = [e for e in self.edits if e.ts_ms > edit.ts_ms - RECENT_MS] + [edit]

    def up_to(self, at_ms: int) -> list[AnnotationEdit]:
        with self.lock:
            return [e for e in self.edits if e.ts_ms <= at_ms]


def standing(
    recent_edits: RecentEdits, store: AnnotationReader, at_ms: int
) -> dict[str, CurrentAnnotation]:
    """The annotations at `at_ms`: the store's, with this process's recent edits applied."""
    current = {c.annotation_id: c for c in store.annotations_at(at_ms)}
    recent = recent_edits.up_to(at_ms)
    if not recent:
        return current
    # The recent edits are the latest of their ids: re-applied on the stored state of those
    # ids (an edit already stored changes nothing when applied again).
    touched = {e.event.annotation_id for e in recent}
    seeds = [
        AnnotationEdit(
            c.created_ms, "", AnnotationCreated(c.annotation_id, c.created_by, c.annotation)
        )
        for c in current.values()
        if c.annotation_id in touched
    ]
    out = {k: v for k, v in current.items() if k not in touched}
    out.update(fold_annotations([*seeds, *recent], at_ms))
    return out
