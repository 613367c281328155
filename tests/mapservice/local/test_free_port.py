"""Ports chosen to be bound later (`free_port`) lie outside the kernel's ephemeral range."""

from __future__ import annotations

import socket

import pytest

from mapservice.local import embedded


def test_a_chosen_port_is_outside_the_ephemeral_range_free_and_not_handed_out_twice() -> None:
    """An ephemeral port can become any process's outgoing connection's local end between
    the choice and a restart's bind: a restarted `up` then failed with "already in use"."""
    ephemeral = embedded.ephemeral_ports()
    if ephemeral is None:
        pytest.skip("this system does not publish its ephemeral port range")
    ports = [embedded.free_port() for _ in range(50)]
    assert len(set(ports)) == len(ports)
    for port in ports:
        assert port not in ephemeral
        assert embedded.LOWEST_CHOSEN_PORT <= port <= 65_535
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))


def test_a_port_in_use_is_passed_over(monkeypatch: pytest.MonkeyPatch) -> None:
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        taken = held.getsockname()[1]
        # Outside a range that covers the rest remain the held port, any others in use
        # after it, and the first free one.
        other = next(p for p in range(taken + 1, 65_536) if embedded._bindable(p))
        monkeypatch.setattr(embedded, "LOWEST_CHOSEN_PORT", taken)
        monkeypatch.setattr(embedded, "ephemeral_ports", lambda: range(other + 1, 65_536))
        monkeypatch.setattr(embedded, "_ports_handed_out", set())
        assert embedded.free_port() == other


def test_without_a_known_range_the_kernel_chooses(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(embedded, "ephemeral_ports", lambda: None)
    port = embedded.free_port()
    with socket.socket() as s:
        s.bind(("127.0.0.1", port))
