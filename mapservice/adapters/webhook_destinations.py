"""Where a webhook's deliveries may connect: a publicly routable address, or one in the
networks the plant names (MAPSERVICE_WEBHOOK_NETWORKS), and never an endpoint of the
service's own dependencies (the store, Kafka, the MQTT broker).

A webhook URL is an operator's, and the processors POST to it from inside the plant's
network: without this, a URL could aim them at the store's HTTP interface, a cloud's
metadata address or any internal service. The check is made on the address each connection
is opened to, after name resolution, by httpcore's network backend (`GuardedBackend`): every
form a URL can name a host in (a name, `localhost`, a decimal, hex, octal or short IPv4, an
IPv6 literal, an IPv4-mapped, 6to4 or NAT64 IPv6) reaches the same check, and a name that
resolved to a public address when the webhook was registered and to an internal one later
is refused at that later connection. Redirects are not followed (the delivery client's own
setting), so a receiver cannot send a delivery on elsewhere.
"""

from __future__ import annotations

import ipaddress
import socket
import ssl
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

import httpcore
import httpx

from mapservice.core.webhooks import IPNetwork, parse_networks
from mapservice.settings import Settings

IPAddress = ipaddress.IPv4Address | ipaddress.IPv6Address
Resolver = Callable[[str, int], list[str]]

_NAT64 = ipaddress.IPv6Network("64:ff9b::/96")
DEFAULT_PORTS = {"http": 80, "https": 443}


class DestinationRefused(ValueError):
    """A webhook may not connect there; the message says why and what to do."""


class Unresolved(DestinationRefused):
    """The host does not resolve (here, now): nothing can be sent to it yet."""


def resolve(host: str, port: int) -> list[str]:
    """Every address `host` resolves to (as the system resolver answers: it also reads the
    numeric forms, so `2130706433` and `0x7f.1` are 127.0.0.1), in its order, once each."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        raise Unresolved(f"the host {host!r} does not resolve: {exc}") from None
    return list(dict.fromkeys(str(info[4][0]).split("%")[0] for info in infos))


def _embedded_ipv4(ip: IPAddress) -> ipaddress.IPv4Address | None:
    """The IPv4 address an IPv6 one carries (mapped, 6to4, NAT64), which is where it goes."""
    if isinstance(ip, ipaddress.IPv4Address):
        return None
    if ip.ipv4_mapped is not None:
        return ip.ipv4_mapped
    if ip.sixtofour is not None:
        return ip.sixtofour
    if ip in _NAT64:
        return ipaddress.IPv4Address(int(ip) & 0xFFFFFFFF)
    return None


def _kind(ip: IPAddress) -> str:
    for name, test in (
        ("a loopback", ip.is_loopback),
        ("a link-local", ip.is_link_local),
        ("an unspecified", ip.is_unspecified),
        ("a multicast", ip.is_multicast),
        ("a private", ip.is_private),
        ("a reserved", ip.is_reserved),
    ):
        if test:
            return name
    return "a non-public"


@dataclass(frozen=True)
class DestinationPolicy:
    """Public addresses, plus `networks`; never an endpoint in `denied` ((address, port) of
    the service's own dependencies, whatever the networks say)."""

    networks: tuple[IPNetwork, ...] = ()
    denied: frozenset[tuple[str, int]] = frozenset()
    resolver: Resolver = field(default=resolve, compare=False)

    def refusal(self, address: str, port: int) -> str | None:
        """Why a webhook may not connect to `address`:`port`, or None if it may. An IPv6
        address that carries an IPv4 one (mapped, 6to4, NAT64) is judged as that IPv4."""
        ip = ipaddress.ip_address(address)
        judged = _embedded_ipv4(ip) or ip
        if (str(judged), port) in self.denied or (str(ip), port) in self.denied:
            return (
                f"{address} port {port} is one of the service's own dependencies "
                "(its store, Kafka or MQTT broker), which webhooks may never reach"
            )
        if any(judged in n for n in self.networks if n.version == judged.version):
            return None
        if judged.is_global and not judged.is_multicast:
            return None
        return (
            f"{address} is {_kind(judged)} address; webhooks reach public addresses "
            "and those in MAPSERVICE_WEBHOOK_NETWORKS (e.g. the plant's receivers' "
            "network, 10.20.0.0/16), which does not hold it"
        )

    def permitted(self, host: str, port: int) -> list[str]:
        """The addresses of `host` a webhook may connect to: all it resolves to, or
        DestinationRefused when any of them is refused (a name that also points inside is
        not half trusted)."""
        addresses = self.resolver(host, port)
        if not addresses:
            raise Unresolved(f"the host {host!r} resolves to no address")
        for address in addresses:
            why = self.refusal(address, port)
            if why is not None:
                shown = "" if address == host.strip("[]") else f"{host} resolves to {address}: "
                raise DestinationRefused(shown + why)
        return addresses

    def check_url(self, url: str) -> None:
        """DestinationRefused unless a webhook may send to `url` (a URL that passed
        `webhook_urls.check_url`)."""
        parts = urlsplit(url)
        self.permitted(parts.hostname or "", parts.port or DEFAULT_PORTS[parts.scheme])


def _endpoint(address: str, default_port: int) -> tuple[str, int] | None:
    """(host, port) of a dependency's address: a URL, or Kafka's [PROTOCOL://]host:port."""
    address = address.strip()
    if not address:
        return None
    parts = urlsplit(address if "://" in address else f"tcp://{address}")
    try:
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname:
        return None
    return parts.hostname, port or DEFAULT_PORTS.get(parts.scheme, default_port)


def dependency_endpoints(settings: Settings) -> list[tuple[str, int]]:
    """The service's own dependencies as (host, port): the store over HTTP, each Kafka
    bootstrap server, the MQTT broker (its TCP and WebSocket listeners), EMQX's REST API."""
    found = [
        _endpoint(settings.clickhouse_dsn if "://" in settings.clickhouse_dsn else "", 8123),
        *(_endpoint(b, 9092) for b in settings.kafka_bootstrap.split(",")),
        _endpoint(settings.mqtt_url, 1883),
        _endpoint(settings.mqtt_ws_url, 80),
        _endpoint(settings.emqx_api_url, 18083),
    ]
    return [e for e in found if e is not None and not e[0].startswith("chdb")]


def destination_policy(settings: Settings, resolver: Resolver = resolve) -> DestinationPolicy:
    """The policy of this process's settings; the dependencies' names are resolved once,
    here (one that does not resolve names nothing a delivery could reach either)."""
    denied: set[tuple[str, int]] = set()
    for host, port in dependency_endpoints(settings):
        try:
            denied.update((str(ipaddress.ip_address(a)), port) for a in resolver(host, port))
        except DestinationRefused:
            continue
    return DestinationPolicy(
        networks=parse_networks(settings.webhook_networks),
        denied=frozenset(denied),
        resolver=resolver,
    )


_deadlines = threading.local()


@contextmanager
def try_within(seconds: float) -> Iterator[None]:
    """Bounds everything this thread's delivery client does inside the block (connecting,
    TLS, sending, reading the answer) to `seconds` in all: httpx's timeouts bound each
    socket operation, so a receiver trickling its answer a byte at a time would hold a
    delivery worker, and every webhook behind it, for ever."""
    _deadlines.at = time.monotonic() + seconds
    try:
        yield
    finally:
        _deadlines.at = None


def _within(timeout: float | None, timed_out: type[Exception]) -> float | None:
    """`timeout` cut to what is left of this thread's deadline (None: none is set)."""
    at: float | None = getattr(_deadlines, "at", None)
    if at is None:
        return timeout
    left = at - time.monotonic()
    if left <= 0:
        raise timed_out("the delivery's time ran out")
    return left if timeout is None else min(timeout, left)


class DeadlineStream(httpcore.NetworkStream):
    """A connection whose every operation ends by the deadline of `try_within`."""

    def __init__(self, stream: httpcore.NetworkStream) -> None:
        self._stream = stream

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._stream.read(max_bytes, _within(timeout, httpcore.ReadTimeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._stream.write(buffer, _within(timeout, httpcore.WriteTimeout))

    def close(self) -> None:
        self._stream.close()

    def start_tls(
        self,
        ssl_context: ssl.SSLContext,
        server_hostname: str | None = None,
        timeout: float | None = None,
    ) -> httpcore.NetworkStream:
        wait = _within(timeout, httpcore.ConnectTimeout)
        return DeadlineStream(self._stream.start_tls(ssl_context, server_hostname, wait))

    def get_extra_info(self, info: str) -> Any:
        return self._stream.get_extra_info(info)


class GuardedBackend(httpcore.NetworkBackend):
    """httpcore's own network backend, connecting only where the policy permits: the host
    of each new connection resolved here, every address checked, then connected to by
    address (TLS still verifies the certificate against the URL's host name)."""

    def __init__(self, policy: DestinationPolicy) -> None:
        self.policy = policy
        self._backend = httpcore.SyncBackend()

    def connect_tcp(
        self,
        host: str,
        port: int,
        timeout: float | None = None,
        local_address: str | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        try:
            addresses = self.policy.permitted(host, port)
        except DestinationRefused as exc:
            raise httpcore.ConnectError(f"refused: {exc}") from None
        error: Exception | None = None
        for address in addresses:
            try:
                wait = _within(timeout, httpcore.ConnectTimeout)
                return DeadlineStream(
                    self._backend.connect_tcp(address, port, wait, local_address, socket_options)
                )
            except (httpcore.ConnectError, httpcore.ConnectTimeout) as exc:
                error = exc
        assert error is not None
        raise error

    def connect_unix_socket(
        self,
        path: str,
        timeout: float | None = None,
        socket_options: Iterable[Any] | None = None,
    ) -> httpcore.NetworkStream:
        raise httpcore.ConnectError("refused: webhooks are sent over TCP only")

    def sleep(self, seconds: float) -> None:
        self._backend.sleep(seconds)


class GuardedTransport(httpx.HTTPTransport):
    """httpx's transport whose connection pool opens connections through `GuardedBackend`
    (httpx takes no network backend of its own; its pool, httpcore's, does)."""

    def __init__(self, policy: DestinationPolicy) -> None:
        super().__init__(trust_env=False)
        self._pool = httpcore.ConnectionPool(
            ssl_context=httpx.create_ssl_context(trust_env=False),
            max_connections=100,
            max_keepalive_connections=20,
            keepalive_expiry=5.0,
            network_backend=GuardedBackend(policy),
        )


def guarded_client(policy: DestinationPolicy, timeout_s: float) -> httpx.Client:
    """The delivery client: no redirect followed, no proxy from the environment, every
    connection through the policy, each try bounded in all by `try_within`."""
    return httpx.Client(
        timeout=timeout_s,
        follow_redirects=False,
        trust_env=False,
        transport=GuardedTransport(policy),
    )
