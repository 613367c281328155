"""The administrator credential: destructive 2019 endpoints (DELETE /chunks, DELETE /meta)
require `Authorization: Bearer <MAPSERVICE_ADMIN_TOKEN>`; the 2019 service let anyone
wipe the database."""

from __future__ import annotations

import secrets

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from mapservice.settings import Settings

from .deps import get_settings

_bearer = HTTPBearer(auto_error=False, description="MAPSERVICE_ADMIN_TOKEN")


def check_admin(request: Request, credentials: HTTPAuthorizationCredentials | None,
                settings: Settings, what: str = "deleting data") -> str:
    """The caller's address, once the bearer token matched; else 401 (none) or 403 (wrong)."""
    if credentials is None:
        raise HTTPException(401, f"{what} needs the administrator credential: send "
                                 "'Authorization: Bearer <MAPSERVICE_ADMIN_TOKEN>'",
                            headers={"WWW-Authenticate": "Bearer"})
    expected = settings.admin_token.get_secret_value().encode()
    if not secrets.compare_digest(credentials.credentials.encode(), expected):
        raise HTTPException(403, "the bearer token is not MAPSERVICE_ADMIN_TOKEN")
    return request.client.host if request.client else "unknown"


def require_admin(
    request: Request,
    credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),
    settings: Settings = Depends(get_settings),
) -> str:
    """Dependency form of `check_admin` for the destructive endpoints."""
    return check_admin(request, credentials, settings)


def optional_bearer(credentials: HTTPAuthorizationCredentials | None = Depends(_bearer)):
    """The bearer credentials if sent (checked only where the operation needs them)."""
    return credentials
