"""The pools' turns (api/fair_share.py) over generated mixes of callers, sessions and bursts:
the bounds always hold (workers, queue, each caller's running and waiting, the memory kept),
no worker idles while a request it may serve waits, a full queue refuses only a caller at
least as far over its share as any other, and callers (and a caller's sessions) that keep
requests waiting are served in turns: none starved, none above its share, however many
sessions or requests one of them brings."""

from __future__ import annotations

from collections import Counter

from hypothesis import given, settings
from hypothesis import strategies as st

from mapservice.api.fair_share import FairShare, Ticket


class Model:
    """A FairShare with every ticket it holds, checked after each step."""

    def __init__(self, turns: FairShare) -> None:
        self.turns = turns
        self.running: list[Ticket] = []
        self.waiting: list[Ticket] = []
        self.granted: list[Ticket] = []  # in grant order (immediate starts and turns)

    def offer(self, caller: str, session: str) -> Ticket:
        ticket = Ticket(caller, session)
        before = Counter(t.caller for t in self.waiting)
        offer = self.turns.offer(ticket)
        if offer.evicted is not None:
            victim = offer.evicted
            assert victim in self.waiting and not victim.granted
            # Only one with at least two more waiting than the newcomer has loses its place.
            if victim.caller == caller:
                sessions = Counter(t.session for t in self.waiting if t.caller == caller)
                assert sessions[victim.session] >= sessions[session] + 2
                line = [
                    t for t in self.waiting if (t.caller, t.session) == (caller, victim.session)
                ]
                assert victim is line[-1]  # the newest of its session
            else:
                assert before[victim.caller] >= before[caller] + 2
            self.waiting.remove(victim)
        if offer.refused == "full":
            # Nobody waiting had two more than this caller: the queue is everyone's share.
            assert len(self.waiting) == self.turns.queue
            assert all(n < before[caller] + 2 for n in before.values())
        elif offer.refused == "caller":
            assert before[caller] == self.turns.caller_queue
        elif ticket.granted:
            self.running.append(ticket)
            self.granted.append(ticket)
        else:
            self.waiting.append(ticket)
        self.check()
        return ticket

    def finish(self, index: int) -> None:
        ticket = self.running.pop(index % len(self.running))
        for granted in self.turns.finish(ticket):
            assert granted in self.waiting and granted.granted
            self.waiting.remove(granted)
            self.running.append(granted)
            self.granted.append(granted)
        self.check()

    def withdraw(self, index: int) -> None:
        ticket = self.waiting.pop(index % len(self.waiting))
        self.turns.withdraw(ticket)
        self.check()

    def check(self) -> None:
        turns = self.turns
        assert turns.running == len(self.running) <= turns.workers
        assert turns.waiting == len(self.waiting) <= turns.queue
        running = Counter(t.caller for t in self.running)
        waiting = Counter(t.caller for t in self.waiting)
        assert all(n <= turns.caller_running for n in running.values())
        assert all(n <= turns.caller_queue for n in waiting.values())
        # Memory: only callers with something running or waiting are remembered.
        assert set(turns.callers) == set(running) | set(waiting)
        # Work-conserving: a free worker means nobody waiting may run.
        if turns.running < turns.workers:
            assert all(running[c] >= turns.caller_running for c in waiting)


ACTIONS = st.lists(
    st.one_of(
        st.tuples(
            st.just("offer"),
            st.integers(0, 5),  # caller
            st.integers(0, 6),  # session
            st.integers(1, 12),  # burst
        ),
        st.tuples(st.just("finish"), st.integers(0, 100), st.integers(1, 4), st.just(0)),
        st.tuples(st.just("withdraw"), st.integers(0, 100), st.just(0), st.just(0)),
    ),
    max_size=80,
)


@settings(max_examples=300, deadline=None)
@given(
    workers=st.integers(1, 4),
    queue=st.integers(0, 24),
    caller_running=st.integers(1, 4),
    caller_queue=st.integers(1, 12),
    actions=ACTIONS,
)
def test_the_bounds_hold_for_any_mix(workers, queue, caller_running, caller_queue, actions) -> None:
    model = Model(FairShare(workers, queue, caller_running, caller_queue))
    for kind, a, b, burst in actions:
        if kind == "offer":
            for _ in range(burst):
                model.offer(f"caller{a}", f"s{b}")
        elif kind == "finish":
            for _ in range(min(b, len(model.running))):
                model.finish(a)
        elif model.waiting:
            model.withdraw(a)
    while model.running:  # everything drains: nothing waits for ever
        model.finish(0)
    assert not model.waiting and not model.turns.callers


@settings(max_examples=200, deadline=None)
@given(
    workers=st.integers(1, 4),
    sessions=st.lists(st.integers(1, 8), min_size=2, max_size=6),
    bursts=st.lists(st.integers(1, 30), min_size=6, max_size=6),
    finishing=st.lists(st.integers(0, 100), min_size=60, max_size=60),
)
def test_backlogged_callers_are_served_in_turns(workers, sessions, bursts, finishing) -> None:
    """Callers, each with its own number of sessions (a hostile one with many) and bursts
    of any size, all keep requests waiting: between two grants to one caller every other
    caller gets one (grant counts never differ by more than one), whatever its sessions;
    within a caller its sessions take turns the same way."""
    callers = [f"caller{i}" for i in range(len(sessions))]
    model = Model(FairShare(workers, queue=200, caller_running=workers, caller_queue=100))

    def keep_waiting() -> None:
        """Every caller's every session keeps a request waiting (a client asking again at
        once): all of them backlogged, the case turns are for."""
        for i, caller in enumerate(callers):
            for s in range(sessions[i]):
                if not any(t.caller == caller and t.session == f"s{s}" for t in model.waiting):
                    model.offer(caller, f"s{s}")

    for i, caller in enumerate(callers):  # everyone busy and waiting before the count starts
        for k in range(max(workers + 1, bursts[i])):
            model.offer(caller, f"s{k % sessions[i]}")
    keep_waiting()
    counted = len(model.granted)
    for index in finishing:
        model.finish(index)
        keep_waiting()
        served = Counter(t.caller for t in model.granted[counted:])
        counts = [served[c] for c in callers]
        assert max(counts) - min(counts) <= 1, counts
    for i, caller in enumerate(callers):
        per_session = Counter(t.session for t in model.granted[counted:] if t.caller == caller)
        counts = [per_session[f"s{s}"] for s in range(sessions[i])]
        assert max(counts) - min(counts) <= 1, (caller, counts)


@given(
    hostile_sessions=st.integers(1, 50),
    queue=st.integers(4, 40),
    caller_queue=st.integers(2, 40),
)
def test_a_caller_filling_the_queue_first_leaves_a_newcomer_its_share(
    hostile_sessions, queue, caller_queue
) -> None:
    """One caller fills the queue (with any number of sessions) before another asks: the
    newcomer's requests take places from it until both hold about half, never refused
    while it has fewer than the hostile caller (less one)."""
    model = Model(FairShare(1, queue, caller_running=1, caller_queue=caller_queue))
    for k in range(queue + caller_queue + 1):
        model.offer("hostile", f"s{k % hostile_sessions}")
    refused = 0
    for _ in range(queue):
        ticket = model.offer("newcomer", "tab")
        waiting = Counter(t.caller for t in model.waiting)
        if ticket not in model.waiting:
            refused += 1
            assert waiting["hostile"] < waiting["newcomer"] + 2 or (
                waiting["newcomer"] == caller_queue
            )
    waiting = Counter(t.caller for t in model.waiting)
    share = min(caller_queue, queue // 2)
    assert waiting["newcomer"] >= share - 1, waiting
