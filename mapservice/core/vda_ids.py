"""The robot id of a VDA 5050 vehicle, derived reversibly from its manufacturer and
serial number (the gateway names its events so; the API reads the names back)."""

from __future__ import annotations

import re

# Robot ids are 1-64 of A-Z a-z 0-9 _ . : @ - . A vehicle's id is
# `<manufacturer>:<serialNumber>`, each escaped: every byte of its UTF-8 outside
# A-Z a-z 0-9 _ . - becomes `@` and two upper-case hex digits (so ':' and '@' in a name are
# escaped and the one ':' separates the two names).
_PLAIN = re.compile(rb"[A-Za-z0-9_.-]")
_ALL_PLAIN = re.compile(r"[A-Za-z0-9_.-]*")  # ASCII ranges: a name that escapes to itself


def _escape(name: str) -> str:
    if _ALL_PLAIN.fullmatch(name):
        return name  # most names: no per-byte work on the gateway's hot path
    return "".join(chr(b) if _PLAIN.fullmatch(bytes([b])) else f"@{b:02X}" for b in name.encode())


def _unescape(escaped: str) -> str:
    return b"".join(
        bytes.fromhex(m[1:]) if m.startswith("@") else m.encode()
        for m in re.findall(r"@[0-9A-F]{2}|[^@]+|@", escaped)
    ).decode()


def robot_id_for(manufacturer: str, serial_number: str) -> str:
    return f"{_escape(manufacturer)}:{_escape(serial_number)}"


def vehicle_of(robot_id: str) -> tuple[str, str] | None:
    """(manufacturer, serialNumber) of a VDA vehicle's robot id; None for other ids."""
    parts = robot_id.split(":")
    if len(parts) != 2 or not all(parts):
        return None
    try:
        decoded = tuple(_unescape(p) for p in parts)
    except UnicodeDecodeError:
        return None
    return decoded if robot_id_for(*decoded) == robot_id else None  # type: ignore[return-value]
