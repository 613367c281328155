"""What a live incident detection found and has not stored yet (incident_tracker.py's and
event_incident_tracker.py's): the findings new or changed and the incidents retracted, taken
to be stored and given back when that failed."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from mapservice.core.incident_model import Incident


class UnstoredFindings:
    """`_note` a finding (each detection says when one is new or changed) and `_drop` an
    incident a later history no longer holds."""

    current: dict[str, Incident]  # by id, the latest finding of each incident held
    found: dict[str, Incident]  # new or changed findings, not taken yet
    retracted: dict[str, Incident]

    def _note(self, incident: Incident) -> None:
        raise NotImplementedError

    def _drop(self, incident: Incident) -> None:
        self.current.pop(incident.incident_id, None)
        self.found.pop(incident.incident_id, None)
        self.retracted[incident.incident_id] = incident

    def take(self) -> tuple[list[Incident], list[Incident]]:
        """The findings to store since the last call: (found or changed, retracted)."""
        found, retracted = list(self.found.values()), list(self.retracted.values())
        self.found.clear()
        self.retracted.clear()
        return found, retracted

    def give_back(self, found: Sequence[Incident], retracted: Sequence[Incident]) -> None:
        """Findings `take` gave that could not be stored: taken again next time, unless a
        later finding of the same incident replaced them."""
        for incident in found:
            if incident.incident_id not in self.retracted:
                self.found.setdefault(incident.incident_id, incident)
        for incident in retracted:
            if incident.incident_id not in self.found:
                self.retracted.setdefault(incident.incident_id, incident)

    def _held_over(self, stored: Iterable[Incident]) -> list[Incident]:
        """What is known of the incidents: those `stored` as found here, each by its
        latest finding held, and those retracted here left out (the store still holds
        them until the retraction is stored: found again from it, one would come back)."""
        known = {i.incident_id: i for i in stored if i.incident_id not in self.retracted}
        known.update(self.current)
        return list(known.values())

    def _replace(self, before: Iterable[Incident], fresh: Iterable[Incident]) -> None:
        """`fresh` found where `before` was: what is not found again is retracted."""
        fresh_ids = set()
        for incident in fresh:
            fresh_ids.add(incident.incident_id)
            self._note(incident)
        for incident in before:
            if incident.incident_id not in fresh_ids:
                self._drop(incident)
