"""Where webhooks may be sent: every internal address, in every form a URL can name it, is
refused when an operator registers it (a 422 saying what to set) and when a delivery
connects (nothing reaches the receiver); what the plant names in MAPSERVICE_WEBHOOK_NETWORKS
is delivered to, the service's own store, Kafka and MQTT endpoints never; a name checked
at registration is checked again where each delivery connects (a name that later points
inside is refused then)."""

from __future__ import annotations

import dataclasses
import ipaddress
import random
import socket

import pytest

from mapservice.adapters.webhook_destinations import (
    DestinationPolicy,
    DestinationRefused,
    Unresolved,
    destination_policy,
)
from mapservice.core.webhooks import Webhook, parse_networks
from mapservice.local.embedded import free_port
from mapservice.processors.webhook_delivery import WebhookDeliveries
from mapservice.settings import Settings
from tests.api.test_webhooks import World
from tests.processors.test_webhook_delivery import POLICY, SECRET, Receiver, started, wait_for

RNG = random.Random(20261201)
LOOPBACK_NET = parse_networks("127.0.0.0/8")
# Ranges no webhook may reach unless named (their own and via IPv6 wrappers below).
INTERNAL_V4 = [
    "127.0.0.0/8",
    "10.0.0.0/8",
    "172.16.0.0/12",
    "192.168.0.0/16",
    "169.254.0.0/16",
    "100.64.0.0/10",
    "0.0.0.0/8",
    "224.0.0.0/4",
    "240.0.0.0/4",
    "192.0.2.0/24",
    "198.18.0.0/15",
]
INTERNAL_V6 = ["::1/128", "fe80::/10", "fc00::/7", "ff00::/8", "::/128"]
PUBLIC = ["8.8.8.8", "93.184.216.34", "2001:4860:4860::8888", "::ffff:1.1.1.1"]


def random_in(network: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    net = ipaddress.ip_network(network)
    return net[RNG.randrange(net.num_addresses)]


def url_hosts(ip: ipaddress.IPv4Address | ipaddress.IPv6Address) -> list[str]:
    """Every way a URL's host can name `ip` (what the system resolver reads as it)."""
    if ip.version == 6:
        return [f"[{ip}]", f"[{ip.exploded}]"]
    n, octets = int(ip), str(ip).split(".")
    forms = [
        str(ip),
        str(n),  # decimal
        hex(n),  # hexadecimal
        ".".join("0" + oct(int(o))[2:] for o in octets),  # octal octets
        f"{octets[0]}.{n & 0xFFFFFF}",  # a.b: the last 24 bits as one number
        f"[::ffff:{ip}]",  # IPv4-mapped
        f"[64:ff9b::{ip}]",  # NAT64
        f"[2002:{n >> 16:x}:{n & 0xFFFF:x}::1]",  # 6to4
    ]
    return forms


def internal_hosts() -> list[str]:
    hosts = ["localhost"]
    for net in INTERNAL_V4:
        hosts += url_hosts(random_in(net))
    for net in INTERNAL_V6:
        hosts += url_hosts(random_in(net))
    hosts.append("[::ffff:169.254.169.254]")
    return hosts


@pytest.mark.parametrize("host", internal_hosts())
def test_every_form_of_an_internal_address_is_refused_at_registration(host) -> None:
    r = World().register({"url": f"http://{host}:8080/hook"})
    assert r.status_code == 422, (host, r.text)
    # Octal octets: the delivery client does not read them, so the URL is malformed first.
    detail = r.json()["detail"]
    assert "MAPSERVICE_WEBHOOK_NETWORKS" in detail or "malformed" in detail, r.text


@pytest.mark.parametrize("host", internal_hosts())
def test_every_form_of_an_internal_address_is_refused_where_a_delivery_connects(host) -> None:
    with pytest.raises(DestinationRefused, match="MAPSERVICE_WEBHOOK_NETWORKS"):
        DestinationPolicy().check_url(f"http://{host}:8080/hook")


@pytest.mark.parametrize("address", PUBLIC)
def test_public_addresses_are_taken(address) -> None:
    host = f"[{address}]" if ":" in address else address
    assert World().register({"url": f"https://{host}/hook"}).status_code == 201
    assert DestinationPolicy().refusal(address, 443) is None


def deliver(policy: DestinationPolicy, url: str, alerts: int = 1) -> WebhookDeliveries:
    return started(
        [Webhook("w1", url, SECRET)], dataclasses.replace(POLICY, destinations=policy), alerts
    )


LOOPBACK_FORMS = ["127.0.0.1", "localhost", "2130706433", "0x7f000001", "0x7f.1", "127.1"]


@pytest.mark.parametrize("host", LOOPBACK_FORMS)
def test_a_receiver_on_an_unnamed_network_gets_nothing_and_one_named_gets_every_alert(
    host,
) -> None:
    """Through the delivery client itself: the receiver is reachable in each form (named,
    every alert arrives), and refused in each (unnamed, nothing arrives, the reason shows)."""
    port = free_port()
    receiver = Receiver(port)
    try:
        refused = deliver(DestinationPolicy(), f"http://{host}:{port}/hook", alerts=2)
        try:
            wait_for(lambda: refused.health()["w1"].paused_reason)
            reason = refused.health()["w1"].paused_reason
            assert "loopback" in reason and "MAPSERVICE_WEBHOOK_NETWORKS" in reason, reason
        finally:
            refused.close()
        assert receiver.requests == []
        named = deliver(DestinationPolicy(networks=LOOPBACK_NET), f"http://{host}:{port}/h", 2)
        try:
            wait_for(lambda: named.queued("w1") == 0)
        finally:
            named.close()
        assert len(receiver.delivered()) == 2
    finally:
        receiver.close()


class Names:
    """A resolver whose answers the test changes (a DNS record changed, or rebound)."""

    def __init__(self, **answers: list[str]) -> None:
        self.answers = {k.replace("_", "."): v for k, v in answers.items()}

    def __call__(self, host: str, port: int) -> list[str]:
        if host in self.answers:
            return self.answers[host]
        try:
            return [str(i[4][0]) for i in socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)]
        except OSError as exc:
            raise Unresolved(str(exc)) from None


def test_a_name_that_later_points_inside_is_refused_at_that_delivery() -> None:
    port = free_port()
    receiver = Receiver(port)
    names = Names(hooks_plant_example=["93.184.216.34"])
    policy = DestinationPolicy(resolver=names)
    url = f"http://hooks.plant.example:{port}/hook"
    try:
        policy.check_url(url)  # registered: it pointed outside
        names.answers["hooks.plant.example"] = ["127.0.0.1"]
        deliveries = deliver(policy, url)
        try:
            wait_for(lambda: deliveries.health()["w1"].paused_reason)
            reason = deliveries.health()["w1"].paused_reason
            assert "hooks.plant.example resolves to 127.0.0.1" in reason, reason
        finally:
            deliveries.close()
        assert receiver.requests == []
        # Named, the same name is connected to by the address it resolves to, Host kept.
        deliveries = deliver(dataclasses.replace(policy, networks=LOOPBACK_NET), url)
        try:
            wait_for(lambda: deliveries.queued("w1") == 0)
        finally:
            deliveries.close()
        assert receiver.requests[0][1]["Host"] == f"hooks.plant.example:{port}"
    finally:
        receiver.close()


def test_a_name_pointing_both_outside_and_inside_is_refused() -> None:
    names = Names(mixed_example=["93.184.216.34", "10.1.2.3"])
    with pytest.raises(DestinationRefused, match=r"resolves to 10\.1\.2\.3"):
        DestinationPolicy(resolver=names).check_url("https://mixed.example/hook")


def test_the_service_s_own_endpoints_are_refused_even_in_a_named_network() -> None:
    store, kafka, mqtt, ws = (free_port() for _ in range(4))
    settings = Settings(
        clickhouse_dsn=f"http://127.0.0.1:{store}",
        kafka_bootstrap=f"PLAINTEXT://localhost:{kafka},127.0.0.2:9",
        mqtt_url=f"mqtt://127.0.0.1:{mqtt}",
        mqtt_ws_url=f"ws://127.0.0.1:{ws}/mqtt",
        webhook_networks="127.0.0.0/8",
    )
    policy = destination_policy(settings)
    for port in (store, kafka, mqtt, ws):
        for host in ("127.0.0.1", "2130706433", "[::ffff:127.0.0.1]"):
            with pytest.raises(DestinationRefused, match="own dependencies"):
                policy.check_url(f"http://{host}:{port}/hook")
    policy.check_url(f"http://127.0.0.1:{free_port()}/hook")  # the plant's receiver beside them
    world = World(clickhouse_dsn=f"http://127.0.0.1:{store}", webhook_networks="127.0.0.0/8")
    r = world.register({"url": f"http://localhost:{store}/?query=DROP+TABLE+x"})
    assert r.status_code == 422 and "own dependencies" in r.json()["detail"], r.text
    assert world.register({"url": f"http://localhost:{free_port()}/hook"}).status_code == 201


def test_a_name_this_api_cannot_resolve_is_taken_and_its_deliveries_say_why() -> None:
    assert World().register({"url": "https://mes.plant.invalid:8443/hooks"}).status_code == 201
    deliveries = deliver(DestinationPolicy(), "https://mes.plant.invalid:8443/hooks")
    try:
        wait_for(lambda: deliveries.health()["w1"].paused_reason)
        assert "does not resolve" in deliveries.health()["w1"].paused_reason
    finally:
        deliveries.close()


@pytest.mark.parametrize("text", ["10.0.0.0/33", "plant", "10.0.0.0/8;192.168.0.0/16"])
def test_a_network_setting_that_is_no_network_stops_the_start_saying_which(text) -> None:
    with pytest.raises(ValueError, match="is not a network"):
        Settings(webhook_networks=text)
