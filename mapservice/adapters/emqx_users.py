"""Robot users in EMQX's built-in database, through EMQX's REST API (v5): what
`BrokerFiles` does for Mosquitto's password file, for the Kubernetes broker.

EMQX hashes the password itself (sha256 with a suffix salt, infra/k8s/platform/emqx.yaml)
and its ACL file already ties every robot's topics to its username, so a robot is one user.
The API key is created in EMQX's dashboard (System -> API Key) or its bootstrap file."""

from __future__ import annotations

from typing import Any
from urllib.parse import quote

import httpx

from .mqtt_auth import (
    GATEWAY_USER,
    PROCESSORS_USER,
    AclTopics,
    RobotCredential,
    check_identity,
    new_password,
)

AUTHENTICATOR = "password_based:built_in_database"
PAGE = 1000


class EmqxError(RuntimeError):
    """EMQX refused or could not be reached; the message says what to do."""


class EmqxUsers:
    def __init__(
        self,
        api_url: str,
        api_key: str,
        api_secret: str,
        topics: AclTopics | None = None,
        authenticator: str = AUTHENTICATOR,
        client: httpx.Client | None = None,
        service_users: tuple[str, ...] = (GATEWAY_USER, PROCESSORS_USER),
    ) -> None:
        if not api_url or not api_key or not api_secret:
            raise EmqxError(
                "EMQX's REST API needs MAPSERVICE_EMQX_API_URL, MAPSERVICE_EMQX_API_KEY "
                "and MAPSERVICE_EMQX_API_SECRET (an API key from the dashboard: "
                "System -> API Key)"
            )
        self.api_url = api_url
        self.topics = topics or AclTopics()
        self.service_users = service_users
        self._users = f"/api/v5/authentication/{quote(authenticator, safe='')}/users"
        self._client = client or httpx.Client(base_url=api_url.rstrip("/"), timeout=10.0)
        self._client.auth = httpx.BasicAuth(api_key, api_secret)

    def _call(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        try:
            resp = self._client.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            raise EmqxError(
                f"EMQX's REST API at {self._client.base_url} did not answer ({exc}); "
                "check MAPSERVICE_EMQX_API_URL (the dashboard port, 18083)"
            ) from exc
        if resp.status_code == 401:
            raise EmqxError(
                "EMQX refused the API key (401): check MAPSERVICE_EMQX_API_KEY and _SECRET"
            )
        return resp

    @staticmethod
    def _refused(resp: httpx.Response, what: str) -> EmqxError:
        try:
            detail = resp.json().get("message", resp.text)
        except ValueError:
            detail = resp.text
        return EmqxError(f"EMQX refused to {what} ({resp.status_code}): {detail[:200]}")

    def add_robot(
        self,
        robot_id: str,
        *,
        legacy_chunks: bool = False,
        rotate: bool = False,
        password: str | None = None,
    ) -> RobotCredential:
        """Creates the robot's user (or, with `rotate`, gives it a new password)."""
        check_identity(robot_id, self.service_users)
        if legacy_chunks:
            raise EmqxError(
                "EMQX's ACL is a file in the ConfigMap mapservice-emqx-acl: allow a "
                "robot the 2019 chunk topic there (the file says how)"
            )
        password = password or new_password()
        if rotate:
            resp = self._call(
                "PUT",
                f"{self._users}/{quote(robot_id, safe='')}",
                json={"password": password, "is_superuser": False},
            )
            if resp.status_code == 404:
                raise EmqxError(f"robot {robot_id!r} has no EMQX user to rotate; add it first")
        else:
            resp = self._call(
                "POST",
                self._users,
                json={"user_id": robot_id, "password": password, "is_superuser": False},
            )
            if resp.status_code == 409:
                raise EmqxError(
                    f"robot {robot_id!r} already has an MQTT credential; "
                    "--rotate gives it a new password"
                )
        if resp.status_code not in (200, 201):
            raise self._refused(resp, f"store robot {robot_id!r}")
        return RobotCredential(
            robot_id, robot_id, password, self.topics.robot_topics(robot_id), False
        )

    def remove_robot(self, robot_id: str) -> bool:
        """Deletes the robot's user; False when it had none. EMQX keeps a connected
        client connected: kick it from the dashboard (Clients) if it must go at once."""
        check_identity(robot_id, self.service_users)
        resp = self._call("DELETE", f"{self._users}/{quote(robot_id, safe='')}")
        if resp.status_code == 404:
            return False
        if resp.status_code != 204:
            raise self._refused(resp, f"remove robot {robot_id!r}")
        return True

    def robots(self) -> list[str]:
        """Every user but the service's, page by page."""
        users, page = [], 1
        while True:
            resp = self._call("GET", self._users, params={"page": page, "limit": PAGE})
            if resp.status_code != 200:
                raise self._refused(resp, "list users")
            body = resp.json()
            users += [u["user_id"] for u in body.get("data", [])]
            if not body.get("meta", {}).get("hasnext"):
                return [u for u in users if u not in self.service_users]
            page += 1

    def legacy_robots(self) -> list[str]:
        return []  # the 2019 chunk topic is granted in EMQX's ACL file, not per user here
