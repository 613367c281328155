"""Who a busy pool serves next: a fair share of its workers for every caller, and within a
caller for every session, instead of first come first served.

A pool has `workers` places and a queue of at most `queue` waiting requests. A caller (a
credential, or a client address when anonymous) runs at most `caller_running` requests at
once and keeps at most `caller_queue` waiting. When a worker frees up, the callers with a
request waiting take turns (round robin, each one request a turn), and within a caller its
sessions (the page's tabs, a script's runs) take turns the same way: two tabs of one
address share that address's turns, and a third caller's turn comes between theirs.

A full queue does not lock newcomers out: a request of a caller (or session) with fewer
waiting than the one with the most takes the place of that one's newest waiting request
(which is refused, "over its share"), so a caller that fills the queue first only ever
holds its share of it. Beyond its share a request is refused at once; everything here is
bounded by `queue` and `workers` (callers and sessions with nothing waiting or running are
forgotten), so a client minting session names or opening connections gains nothing: its
sessions split its one caller's turns and places.

Pure bookkeeping, no clock and no I/O: admission.py waits on it and times out.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Literal

Refusal = Literal["caller", "full"]


@dataclass(eq=False)
class Ticket:
    """One request: whose, and (once decided) whether it runs."""

    caller: str
    session: str = ""
    granted: bool = False


@dataclass
class _Caller:
    running: int = 0
    waiting: int = 0
    # session -> its waiting tickets, oldest first; the order of the keys is the turn order.
    sessions: OrderedDict[str, deque[Ticket]] = field(default_factory=OrderedDict)


@dataclass
class Offer:
    """What became of an offered ticket: it runs now (`refused` None and `ticket.granted`),
    waits, or is refused (`refused` says why); `evicted` lost its place to it."""

    refused: Refusal | None = None
    evicted: Ticket | None = None


class FairShare:
    """The queue and the turns of one pool (module docstring)."""

    def __init__(self, workers: int, queue: int, caller_running: int, caller_queue: int) -> None:
        self.workers, self.queue = workers, queue
        self.caller_running, self.caller_queue = caller_running, caller_queue
        self.running = 0
        self.waiting = 0
        # caller -> its state; the order of the keys is the callers' turn order.
        self.callers: OrderedDict[str, _Caller] = OrderedDict()

    def offer(self, ticket: Ticket) -> Offer:
        """Runs `ticket` now if a worker is free and its caller below its share, else queues
        it, taking the place of a request over its share when the queue is full."""
        who = self.callers.setdefault(ticket.caller, _Caller())
        if self.running < self.workers and who.running < self.caller_running and not who.waiting:
            self._start(ticket, who)
            return Offer()
        evicted = None
        if who.waiting >= self.caller_queue:
            evicted = self._push_out_within(who, ticket.session)
            if evicted is None:
                self._forget_if_idle(ticket.caller)
                return Offer(refused="caller")
        elif self.waiting >= self.queue:
            evicted = self._push_out_across(who)
            if evicted is None:
                self._forget_if_idle(ticket.caller)
                return Offer(refused="full")
        who.sessions.setdefault(ticket.session, deque()).append(ticket)
        who.waiting += 1
        self.waiting += 1
        return Offer(evicted=evicted)

    def withdraw(self, ticket: Ticket) -> None:
        """A waiting ticket leaves the queue (it waited too long, or its client left)."""
        who = self.callers.get(ticket.caller)
        line = who.sessions.get(ticket.session) if who else None
        if who is None or line is None or ticket not in line:
            return
        line.remove(ticket)
        self._left_queue(ticket, who)
        self._forget_if_idle(ticket.caller)

    def finish(self, ticket: Ticket) -> list[Ticket]:
        """A granted ticket is done: its worker goes to the next turns; the tickets granted."""
        who = self.callers[ticket.caller]
        who.running -= 1
        self.running -= 1
        self._forget_if_idle(ticket.caller)
        return self._dispatch()

    def at_own_cap(self, caller: str) -> bool:
        """Whether `caller` runs all it may: its waiting is its own doing, not the pool's."""
        who = self.callers.get(caller)
        return who is not None and who.running >= self.caller_running

    def _dispatch(self) -> list[Ticket]:
        granted = []
        while self.running < self.workers:
            turn = next(
                (
                    name
                    for name, who in self.callers.items()
                    if who.waiting and who.running < self.caller_running
                ),
                None,
            )
            if turn is None:
                break
            who = self.callers[turn]
            self.callers.move_to_end(turn)  # its turn taken: last in the round
            session, line = next(iter(who.sessions.items()))
            ticket = line.popleft()
            who.sessions.move_to_end(session)
            self._left_queue(ticket, who)
            self._start(ticket, who)
            granted.append(ticket)
        return granted

    def _start(self, ticket: Ticket, who: _Caller) -> None:
        ticket.granted = True
        who.running += 1
        self.running += 1

    def _left_queue(self, ticket: Ticket, who: _Caller) -> None:
        if not who.sessions[ticket.session]:
            del who.sessions[ticket.session]
        who.waiting -= 1
        self.waiting -= 1

    def _push_out_within(self, who: _Caller, session: str) -> Ticket | None:
        """The newest waiting request of the caller's session with the most waiting, if that
        session has at least two more than `session` would (else the newcomer is the one
        over its share)."""
        mine = len(who.sessions.get(session, ()))
        longest = max(who.sessions, key=lambda s: len(who.sessions[s]))
        if len(who.sessions[longest]) < mine + 2:
            return None
        ticket = who.sessions[longest].pop()
        self._left_queue(ticket, who)
        return ticket

    def _push_out_across(self, who: _Caller) -> Ticket | None:
        """The newest waiting request of the caller with the most waiting (of its longest
        session), if it has at least two more than `who` would."""
        name = max(self.callers, key=lambda c: self.callers[c].waiting)
        longest = self.callers[name]
        if longest.waiting < who.waiting + 2:
            return None
        session = max(longest.sessions, key=lambda s: len(longest.sessions[s]))
        ticket = longest.sessions[session].pop()
        self._left_queue(ticket, longest)
        return ticket

    def _forget_if_idle(self, caller: str) -> None:
        who = self.callers.get(caller)
        if who is not None and not who.running and not who.waiting:
            del self.callers[caller]
