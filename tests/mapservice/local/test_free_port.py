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


def test_stacks_side_by_side_choose_from_disjoint_slices(monkeypatch: pytest.MonkeyPatch) -> None:
    """Two workers' stacks pick ports at random; without slices one could take a port the
    other chose and had not bound yet."""
    monkeypatch.setattr(embedded, "ephemeral_ports", lambda: range(32_768, 61_000))
    chosen: list[set[int]] = []
    for k in range(3):
        monkeypatch.setenv(embedded.PORT_SLICE_ENV, f"{k}/3")
        monkeypatch.setattr(embedded, "_ports_handed_out", set())
        ports = {embedded.free_port() for _ in range(300)}
        low, high = range(10_000, 32_768), range(61_000, 65_536)
        mine = {*low[k * len(low) // 3 : (k + 1) * len(low) // 3]}
        mine |= {*high[k * len(high) // 3 : (k + 1) * len(high) // 3]}
        assert ports <= mine
        chosen.append(ports)
    assert all(not chosen[a] & chosen[b] for a in range(3) for b in range(a + 1, 3))


@pytest.mark.parametrize("value", ["", "2", "3/3", "-1/2", "a/b", "1/0"])
def test_a_missing_or_malformed_slice_means_every_candidate(
    value: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(embedded.PORT_SLICE_ENV, value)
    assert embedded._slice(range(10_000, 20_000)) == range(10_000, 20_000)


def test_a_stack_never_chooses_a_port_it_was_given(
    monkeypatch: pytest.MonkeyPatch, tmp_path
) -> None:
    """`up --mqtt-port P` binds P only after its demo week is written; meanwhile P looks
    free, and the ports `up` chose for its own parts (Kafka, its controller, the ClickHouse
    server, health) must not be P: once, the MQTT broker then found its port taken. Here
    the range to choose from holds only the given ports and as many others as the stack
    needs: each given port is its component's, every chosen one another."""
    from mapservice.local.stack import Stack

    monkeypatch.setattr(embedded, "_ports_handed_out", set())
    free = [p for p in range(20_000, 21_000) if embedded._bindable(p)][:7]
    given = {"api_port": free[0], "mqtt_port": free[1], "health_port": free[2]}
    monkeypatch.setattr(embedded, "LOWEST_CHOSEN_PORT", free[0])
    monkeypatch.setattr(embedded, "ephemeral_ports", lambda: range(free[-1] + 1, 65_536))
    monkeypatch.delenv(embedded.PORT_SLICE_ENV, raising=False)
    stack = Stack(tmp_path / "stack", mqtt="mosquitto", apart=True, **given)
    assert {k: getattr(stack, k) for k in given} == given
    chosen = [
        stack.kafka_port,
        stack.mqtt_ws_port,
        stack.clickhouse_port,
        stack.processors_health_port,
    ]
    assert not set(chosen) & set(given.values()), (chosen, given)
    assert len(set(chosen)) == len(chosen)
