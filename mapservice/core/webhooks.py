"""Webhooks an operator registers for incident alerts: what a valid one is, how a delivery
is signed (and how a receiver checks it), how long a failed one waits before its next
try, and when one that keeps failing is paused (its URL's check is an adapter's,
mapservice/adapters/webhook_urls.py: parsing a URL is no core business).

Signing: the body is signed with HMAC-SHA256 under the webhook's secret, over
`<timestamp>.<body>` (the timestamp in whole seconds since the epoch, sent in
`X-Mapservice-Timestamp`), sent as `X-Mapservice-Signature: sha256=<hex>`. The timestamp
inside the signature stops a captured delivery from being replayed later: a receiver
refuses a timestamp further than its tolerance from its own clock (`verify`).

A webhook's secret is derived, not stored: HMAC-SHA256 of its id under the service's
signing key (`derived_secret`). The API shows it to the operator who registers the webhook;
the processors derive it again for each delivery, so no table holds a secret, and a new
signing key changes every webhook's secret at once.
"""

from __future__ import annotations

import hashlib
import hmac
import ipaddress
import re
from collections.abc import Mapping
from dataclasses import dataclass

SIGNATURE_HEADER = "X-Mapservice-Signature"
TIMESTAMP_HEADER = "X-Mapservice-Timestamp"
WEBHOOK_ID_HEADER = "X-Mapservice-Webhook"
DELIVERY_HEADER = "X-Mapservice-Delivery"
SECRET_MIN_CHARS = 16

IPNetwork = ipaddress.IPv4Network | ipaddress.IPv6Network


def parse_networks(text: str) -> tuple[IPNetwork, ...]:
    """MAPSERVICE_WEBHOOK_NETWORKS: CIDRs separated by commas or spaces ("" for none)."""
    out: list[IPNetwork] = []
    for part in text.replace(",", " ").split():
        try:
            out.append(ipaddress.ip_network(part, strict=False))
        except ValueError as exc:
            raise ValueError(
                f"{part!r} is not a network (write e.g. 10.20.0.0/16): {exc}"
            ) from None
    return tuple(out)


SECRET_MAX_CHARS = 256
# A secret is text a plant's system can keep in its configuration: printable ASCII.
_SECRET = re.compile(r"[\x21-\x7e]+")


def signature(secret: str, timestamp_s: int, body: bytes) -> str:
    """`sha256=<hex>` of HMAC-SHA256(secret, f"{timestamp_s}." + body)."""
    mac = hmac.new(secret.encode(), f"{timestamp_s}.".encode() + body, hashlib.sha256)
    return "sha256=" + mac.hexdigest()


def derived_secret(signing_key: str, webhook_id: str) -> str:
    """The secret a webhook's deliveries are signed with: hex HMAC-SHA256 of its id under
    the service's signing key (64 characters, so a valid secret, `check_secret`)."""
    if not signing_key:
        raise ValueError("no signing key: webhook secrets cannot be derived")
    return hmac.new(signing_key.encode(), webhook_id.encode(), hashlib.sha256).hexdigest()


def signed_headers(secret: str, timestamp_s: int, body: bytes) -> dict[str, str]:
    return {
        "Content-Type": "application/json",
        TIMESTAMP_HEADER: str(timestamp_s),
        SIGNATURE_HEADER: signature(secret, timestamp_s, body),
    }


def verify(
    secret: str, headers: Mapping[str, str], body: bytes, now_s: float, tolerance_s: float = 300
) -> bool:
    """Whether a delivery is authentic and fresh: what a receiver runs (headers looked up
    case-insensitively, as HTTP names them)."""
    lower = {k.lower(): v for k, v in headers.items()}
    sent = lower.get(SIGNATURE_HEADER.lower(), "")
    try:
        timestamp_s = int(lower.get(TIMESTAMP_HEADER.lower(), ""))
    except ValueError:
        return False
    if abs(now_s - timestamp_s) > tolerance_s:
        return False
    return hmac.compare_digest(sent, signature(secret, timestamp_s, body))


def backoff_s(attempt: int, base_s: float, cap_s: float) -> float:
    """The wait before try `attempt + 1` after `attempt` failed tries (1, 2, ...):
    base, 2 base, 4 base, ... at most `cap_s`."""
    if attempt < 1:
        raise ValueError("attempt counts from 1")
    return float(min(cap_s, base_s * 2.0 ** min(attempt - 1, 62)))


def check_secret(secret: str) -> str:
    if not SECRET_MIN_CHARS <= len(secret) <= SECRET_MAX_CHARS:
        raise ValueError(
            f"the secret must be {SECRET_MIN_CHARS} to {SECRET_MAX_CHARS} characters long"
        )
    if not _SECRET.fullmatch(secret):
        raise ValueError("the secret must be printable ASCII without spaces")
    return secret


@dataclass(frozen=True)
class Webhook:
    """A registered webhook: where to, which kinds (empty: all), and its signing secret."""

    webhook_id: str
    url: str
    secret: str
    kinds: frozenset[str] = frozenset()

    def wants(self, kind: str) -> bool:
        return not self.kinds or kind in self.kinds


@dataclass
class WebhookHealth:
    """A webhook's delivery state: active, or paused with why (a delivery failed every one
    of its tries: the receiver keeps failing, and trying on would only fill the queue and
    the logs); the last error; counts. A paused webhook's deliveries wait in the queue
    (within its bound) until an operator resumes it: then they are sent, oldest first."""

    delivered: int = 0
    failed_tries: int = 0
    dropped: int = 0
    last_error: str = ""
    paused_reason: str = ""
    last_try_ms: int = 0  # when the last try ended (0: none yet)
    last_result: str = ""  # of that try: "delivered" or its error

    @property
    def state(self) -> str:
        return "paused" if self.paused_reason else "active"

    def succeeded(self, at_ms: int) -> None:
        self.delivered += 1
        self.last_try_ms, self.last_result = at_ms, "delivered"

    def tried_and_failed(self, error: str, at_ms: int) -> None:
        self.failed_tries += 1
        self.last_error = error
        self.last_try_ms, self.last_result = at_ms, error

    def pause(self, tries: int) -> None:
        self.paused_reason = f"a delivery failed {tries} tries in a row; last: {self.last_error}"

    def resume(self) -> None:
        self.paused_reason = ""
