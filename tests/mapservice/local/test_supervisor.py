"""The supervisor of `mapservice up`: an exited component is restarted after an exponential
backoff, reported, and its backoff resets once it stays up (a fake clock, no processes)."""

from __future__ import annotations

from mapservice.local.supervisor import Supervisor, backoff_s


class Fake:
    def __init__(self) -> None:
        self.now = 0.0
        self.alive = {"sim": True, "gateway": True}
        self.restarted: list[str] = []
        self.fail_next = 0
        self.messages: list[str] = []

    def restart(self, name: str) -> None:
        if self.fail_next:
            self.fail_next -= 1
            raise RuntimeError("port busy")
        self.restarted.append(name)
        self.alive[name] = True

    def supervisor(self) -> Supervisor:
        return Supervisor(
            lambda n: self.alive[n],
            {n: (lambda n=n: self.restart(n)) for n in self.alive},
            report=self.messages.append,
            clock=lambda: self.now,
            healthy_after_s=60,
        )


def test_backoff_doubles_up_to_the_cap() -> None:
    """1, 2, 4, 8 s ... and never more than the cap."""
    assert [backoff_s(n) for n in (1, 2, 3, 4)] == [1, 2, 4, 8]
    assert backoff_s(30, cap_s=60) == 60


def test_an_exited_component_is_restarted_after_its_backoff_and_said() -> None:
    """Only the exited component restarts, not before its backoff; both steps are reported."""
    f = Fake()
    sup = f.supervisor()
    f.alive["sim"] = False
    sup.check()
    assert f.restarted == [] and "sim exited; restarting it in 1 s" in f.messages[0]
    f.now = 0.5
    sup.check()
    assert f.restarted == []
    f.now = 1.0
    sup.check()
    assert f.restarted == ["sim"] and f.messages[-1] == "sim restarted"


def test_repeated_failures_back_off_longer_and_reset_after_a_healthy_minute() -> None:
    """A component that keeps exiting waits 1, 2, 4 s; a failing restart backs off too; after
    a minute up, the next exit waits 1 s again."""
    f = Fake()
    sup = f.supervisor()
    waits = []
    for _ in range(3):
        f.alive["gateway"] = False
        sup.check()
        waits.append(sup.watched["gateway"].restart_at - f.now)
        f.now = sup.watched["gateway"].restart_at
        sup.check()
    assert waits == [1, 2, 4] and f.restarted == ["gateway"] * 3
    f.alive["gateway"], f.fail_next = False, 1
    sup.check()
    f.now = sup.watched["gateway"].restart_at
    sup.check()  # the restart itself fails: failure 5, 16 s
    assert "did not start again (port busy)" in f.messages[-1]
    assert sup.watched["gateway"].restart_at - f.now == 16
    f.now = sup.watched["gateway"].restart_at
    sup.check()
    f.now += 61
    sup.check()  # up for a minute: healthy again
    f.alive["gateway"] = False
    sup.check()
    assert sup.watched["gateway"].restart_at - f.now == 1
