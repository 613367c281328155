"""Who a caller is: the bearer tokens of a process, the role each one holds, the scopes a
role grants, and the decision whether a token opens a scope (`decide`). The routes declare
their scopes with the dependencies in `access.py`; `access_guard.py` applies the rest.

Credentials are bearer tokens (`Authorization: Bearer <token>`), each with a role:

| role    | may                                   | setting                          |
| ------- | ------------------------------------- | -------------------------------- |
| reader  | read                                  | MAPSERVICE_API_READER_TOKENS     |
| writer  | read, the 2019 REST writes (robots)   | MAPSERVICE_API_WRITER_TOKENS     |
| robot   | a writer bound to one robotId: chunks | MAPSERVICE_API_ROBOT_TOKENS      |
|         | only under its own id (the handler)   | (robotId=token pairs)            |
| operator| read, edit annotations, command robots| MAPSERVICE_API_OPERATOR_TOKENS   |
| admin   | everything: deletes, the map geometry | MAPSERVICE_ADMIN_TOKEN           |
| metrics | /metrics only (the scraper)           | MAPSERVICE_API_METRICS_TOKEN     |

Reads need no credential unless MAPSERVICE_API_READ_ACCESS=token; while they are open, a
token that is none of these is ignored on reads. Elsewhere no credential is a 401, a token
that is none of these a 401 too (RFC 6750 `invalid_token`), a valid token without the scope
a 403.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from enum import Enum

from fastapi import HTTPException

from mapservice.settings import Settings, robot_tokens, token_list


class Scope(str, Enum):
    PUBLIC = "public"  # probes and the UI's static pages: no data
    READ = "read"  # history and map reads: open or token (MAPSERVICE_API_READ_ACCESS)
    WRITE = "write"  # the 2019 REST writes: a writer (robot) token or the admin token
    ADMIN = "admin"  # deletes, changing the map's geometry: the admin token
    OPERATE = "operator"  # shaping the floor (annotations), commanding robots: an operator token or the admin's
    METRICS = "metrics"  # /metrics (MAPSERVICE_API_METRICS_ACCESS)


GRANTS: dict[str, frozenset[Scope]] = {
    "reader": frozenset({Scope.READ}),
    "writer": frozenset({Scope.READ, Scope.WRITE}),
    "robot": frozenset({Scope.READ, Scope.WRITE}),  # and only as itself: Caller.robot_id
    "operator": frozenset({Scope.READ, Scope.OPERATE}),
    "admin": frozenset({Scope.READ, Scope.WRITE, Scope.ADMIN, Scope.OPERATE, Scope.METRICS}),
    "metrics": frozenset({Scope.METRICS}),
}
# The setting each role's tokens come from, for the answers that say which token to send.
ROLE_SETTINGS: dict[str, str] = {
    "reader": "MAPSERVICE_API_READER_TOKENS",
    "writer": "MAPSERVICE_API_WRITER_TOKENS",
    "robot": "MAPSERVICE_API_ROBOT_TOKENS",
    "operator": "MAPSERVICE_API_OPERATOR_TOKENS",
    "admin": "MAPSERVICE_ADMIN_TOKEN",
    "metrics": "MAPSERVICE_API_METRICS_TOKEN",
}


def holders(scope: Scope) -> tuple[str, ...]:
    """The roles that hold `scope`, in GRANTS' order."""
    return tuple(role for role, scopes in GRANTS.items() if scope in scopes)


def tokens_of(roles: tuple[str, ...]) -> str:
    """'a reader, writer or admin token (their settings)': the words a refusal names."""
    if not roles:
        raise ValueError("no role given: name at least one role")
    named = roles[0] if len(roles) == 1 else f"{', '.join(roles[:-1])} or {roles[-1]}"
    article = "an" if named[0] in "aeiou" else "a"
    settings = ", ".join(ROLE_SETTINGS[role] for role in roles)
    return f"{article} {named} token ({settings})"


# Who may open each scope, derived from GRANTS so that what a refusal says cannot drift from
# what the check does (PUBLIC is held by no role: nobody is ever refused it).
WHO_MAY: dict[Scope, str] = {scope: tokens_of(holders(scope)) for scope in Scope if holders(scope)}
# Browsers connect to /api/v1/live without headers of their own: they offer these two
# WebSocket subprotocols, the second carrying the token; the first is the one accepted.
LIVE_SUBPROTOCOL = "mapservice.live"
TOKEN_SUBPROTOCOL = "bearer."


@dataclass(frozen=True)
class Caller:
    """Who sent a request: a role (None: anonymous) and a name for logs and rate limits
    that identifies the credential without revealing it."""

    role: str | None
    name: str
    robot_id: str | None = None  # a robot token's robot: it writes only as this robot

    def may(self, scope: Scope) -> bool:
        return self.role is not None and scope in GRANTS[self.role]


def _digest(token: str) -> bytes:
    # Looked up by SHA-256, not compared character by character: the time a lookup takes
    # says nothing about how much of a guessed token was right.
    return hashlib.sha256(token.encode()).digest()


class Credentials:
    """The tokens of a process, by digest. Empty settings mean no such credential."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self._roles: dict[bytes, str] = {}
        self._robots = {
            _digest(token): robot
            for token, robot in robot_tokens(settings.api_robot_tokens).items()
        }
        # Later roles win when one token is listed twice: admin above all.
        for role, secret in (
            ("metrics", settings.api_metrics_token),
            ("reader", settings.api_reader_tokens),
            ("writer", settings.api_writer_tokens),
            ("operator", settings.api_operator_tokens),
            ("admin", settings.admin_token),
        ):
            for token in token_list(secret):
                self._roles[_digest(token)] = role

    def identify(self, token: str | None, address: str) -> tuple[Caller, bool]:
        """(caller, valid): anonymous by address without a token; valid False when a token
        was sent that is none of ours."""
        if not token:
            return Caller(None, f"anonymous@{address}"), True
        digest = _digest(token)
        role = self._roles.get(digest)
        if role is None and digest in self._robots:
            robot = self._robots[digest]
            return Caller("robot", f"robot:{robot}:{digest[:6].hex()}", robot), True
        if role is None:
            return Caller(None, f"anonymous@{address}"), False
        return Caller(role, f"{role}:{digest[:6].hex()}"), True


def bearer_token(authorization: str | None) -> str | None:
    if not authorization:
        return None
    scheme, _, token = authorization.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def subprotocol_token(offered: str) -> str | None:
    """A browser's token on a WebSocket: the subprotocol `bearer.<token>`."""
    for protocol in offered.split(","):
        protocol = protocol.strip()
        if protocol.startswith(TOKEN_SUBPROTOCOL):
            return protocol[len(TOKEN_SUBPROTOCOL) :] or None
    return None


def client_address(client: tuple[str, int] | None) -> str:
    """The client's host from an ASGI (host, port) pair or Starlette's Address."""
    return client[0] if client else "unknown"


def denied(status: int, detail: str, error: str | None = None) -> HTTPException:
    challenge = 'Bearer realm="mapservice"' + (f', error="{error}"' if error else "")
    return HTTPException(status, detail, headers={"WWW-Authenticate": challenge})


def decide(
    credentials: Credentials, scope: Scope, token: str | None, address: str, what: str
) -> Caller:
    """The caller if `token` opens `scope`; else the HTTPException to answer (401, 403, 404)."""
    settings = credentials.settings
    caller, valid = credentials.identify(token, address)
    if scope is Scope.PUBLIC:
        return caller
    if scope is Scope.METRICS:
        if settings.metrics_access == "off":
            raise HTTPException(404, "metrics are off (MAPSERVICE_API_METRICS_ACCESS=off)")
        if settings.metrics_access == "open":
            return caller
    if scope is Scope.READ and settings.api_read_access == "open":
        # Open means open: a stale token (a browser's, a robot's after a rotation) does not
        # turn away a read anyone may make; its writes still get the 401 that says so.
        return caller
    if not valid:
        raise denied(
            401, "the bearer token is not one of this service's credentials", "invalid_token"
        )
    if caller.role is None:
        raise denied(401, f"{what} needs {WHO_MAY[scope]}: send 'Authorization: Bearer <token>'")
    if not caller.may(scope):
        raise denied(
            403,
            f"this {caller.role} token may not: {what} needs {WHO_MAY[scope]}",
            "insufficient_scope",
        )
    return caller
