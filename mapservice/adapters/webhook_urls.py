"""Which URLs a webhook may be sent to: http or https, a host, no credentials, bounded."""

from __future__ import annotations

import re
from urllib.parse import urlsplit

import httpx

URL_MAX_CHARS = 2048
_HOST = re.compile(r"[A-Za-z0-9.\-\[\]:]+")


def check_url(url: str) -> str:
    """The URL if a webhook may be sent to it, else ValueError saying why: http or https,
    a host, no credentials (a URL is listed to every operator and logged; the secret is the
    credential), no fragment, at most URL_MAX_CHARS."""
    if len(url) > URL_MAX_CHARS:
        raise ValueError(f"the URL is longer than {URL_MAX_CHARS} characters")
    if any(c.isspace() or ord(c) < 0x20 or ord(c) == 0x7F for c in url):
        raise ValueError("the URL holds whitespace or control characters")
    try:
        parts = urlsplit(url)
        port = parts.port  # raises on a port that is no number or out of range
    except ValueError as exc:
        raise ValueError(f"the URL is malformed: {exc}") from None
    if parts.scheme not in ("http", "https"):
        raise ValueError("the URL must be http:// or https://")
    if parts.username is not None or parts.password is not None or "@" in parts.netloc:
        raise ValueError("the URL must not hold credentials: the secret signs each delivery")
    host = parts.hostname or ""
    if not host or not _HOST.fullmatch(host):
        raise ValueError("the URL has no valid host")
    if port == 0:
        raise ValueError("the URL's port must be 1 to 65535")
    if parts.fragment or url.endswith("#"):
        raise ValueError("the URL must not have a fragment")
    try:
        httpx.URL(url)  # the delivery client's own parser: what it refuses is never sent
    except httpx.InvalidURL as exc:
        raise ValueError(f"the URL is malformed: {exc}") from None
    return url
