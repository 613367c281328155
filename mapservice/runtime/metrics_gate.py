"""Who may read a component's /metrics on its health port: the rule the API applies to its
own /metrics (MAPSERVICE_API_METRICS_ACCESS with the metrics or the admin token), for the
gateway and the processors, whose health port is reachable wherever their pod is."""

from __future__ import annotations

import hashlib
import hmac
from collections.abc import Callable

from mapservice.settings import Settings, token_list

# (status, reason) to answer instead of the metrics; None: serve them.
Refusal = tuple[int, str] | None


def metrics_gate(settings: Settings) -> Callable[[str | None], Refusal]:
    """A check of an `Authorization` header value against the settings' metrics rule."""
    access = settings.metrics_access
    digests = [
        hashlib.sha256(t.encode()).digest()
        for secret in (settings.api_metrics_token, settings.admin_token)
        for t in token_list(secret)
    ]

    def check(authorization: str | None) -> Refusal:
        if access == "off":
            return 404, "metrics are off (MAPSERVICE_API_METRICS_ACCESS=off)"
        if access == "open":
            return None
        scheme, _, token = (authorization or "").partition(" ")
        if scheme.lower() != "bearer" or not token.strip():
            return 401, (
                "/metrics needs the metrics or the admin token: send "
                "'Authorization: Bearer <token>' (MAPSERVICE_API_METRICS_TOKEN)"
            )
        digest = hashlib.sha256(token.strip().encode()).digest()
        # Compared by digest in constant time: the answer's timing says nothing of the token.
        if not any(hmac.compare_digest(digest, d) for d in digests):
            return 401, "the bearer token is not one of this service's metrics credentials"
        return None

    return check
