"""One contract for every place robots' MQTT users live: Mosquitto's password file
(`BrokerFiles`) and EMQX's built-in database (`EmqxUsers`, here against a fake EMQX that
answers as EMQX 5's REST API does: 201/409 on create, 200/404 on update, 204/404 on delete,
pages with `meta.hasnext`; apps/emqx_auth/src/emqx_authn/emqx_authn_api.erl). The fake
covers the requests we send and EMQX's documented answers, not EMQX itself: no EMQX runs
here."""

from __future__ import annotations

import base64
import json
from urllib.parse import unquote

import httpx
import pytest

from mapservice.adapters import emqx_users
from mapservice.adapters.emqx_users import EmqxError, EmqxUsers
from mapservice.adapters.mqtt_auth import BrokerFiles, verify_password

KEY, SECRET = "key-1", "secret-1"
USERS_PATH = "/api/v5/authentication/password_based%3Abuilt_in_database/users"


class FakeEmqx:
    """EMQX 5's user endpoints for the built-in database, in memory."""

    def __init__(self) -> None:
        self.users: dict[str, str] = {}  # user_id -> password (EMQX would keep a hash)
        self.requests: list[httpx.Request] = []

    def handle(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        expected = "Basic " + base64.b64encode(f"{KEY}:{SECRET}".encode()).decode()
        if request.headers.get("authorization") != expected:
            return httpx.Response(
                401, json={"code": "BAD_API_KEY_OR_SECRET", "message": "Check api_key/api_secret"}
            )
        path = request.url.raw_path.decode().split("?")[0]
        if not path.startswith(USERS_PATH):
            return httpx.Response(404, json={"code": "NOT_FOUND", "message": "no such path"})
        user = unquote(path[len(USERS_PATH) + 1 :]) if len(path) > len(USERS_PATH) else None
        body = json.loads(request.content) if request.content else {}
        if request.method == "POST" and user is None:
            if body["user_id"] in self.users:
                return httpx.Response(
                    409, json={"code": "ALREADY_EXISTS", "message": "User already exists"}
                )
            self.users[body["user_id"]] = body["password"]
            return httpx.Response(201, json={"user_id": body["user_id"], "is_superuser": False})
        if request.method == "PUT" and user is not None:
            if user not in self.users:
                return httpx.Response(404, json={"code": "NOT_FOUND", "message": "User not found"})
            self.users[user] = body["password"]
            return httpx.Response(200, json={"user_id": user, "is_superuser": False})
        if request.method == "DELETE" and user is not None:
            if self.users.pop(user, None) is None:
                return httpx.Response(404, json={"code": "NOT_FOUND", "message": "User not found"})
            return httpx.Response(204)
        if request.method == "GET" and user is None:
            page, limit = int(request.url.params["page"]), int(request.url.params["limit"])
            ids = list(self.users)
            chunk = ids[(page - 1) * limit : page * limit]
            return httpx.Response(
                200,
                json={
                    "data": [{"user_id": u, "is_superuser": False} for u in chunk],
                    "meta": {
                        "page": page,
                        "limit": limit,
                        "count": len(ids),
                        "hasnext": page * limit < len(ids),
                    },
                },
            )
        return httpx.Response(405, json={"code": "METHOD_NOT_ALLOWED", "message": request.method})


class Registry:
    """A registry under test and a way to check a stored password, whatever its backend."""

    def __init__(self, kind: str, tmp_path) -> None:
        if kind == "mosquitto":
            self.store = BrokerFiles(tmp_path / "passwd", tmp_path / "acl")
            self.password_ok = lambda robot, pw: verify_password(
                pw,
                dict(line.split(":", 1) for line in self.store.password_file.read_text().split())[
                    robot
                ],
            )
        else:
            self.fake = FakeEmqx()
            client = httpx.Client(
                base_url="http://emqx:18083", transport=httpx.MockTransport(self.fake.handle)
            )
            self.store = EmqxUsers("http://emqx:18083", KEY, SECRET, client=client)
            self.password_ok = lambda robot, pw: self.fake.users.get(robot) == pw


@pytest.fixture(params=["mosquitto", "emqx"])
def registry(request, tmp_path) -> Registry:
    return Registry(request.param, tmp_path)


def test_an_added_robot_gets_a_credential_for_its_own_topics(registry) -> None:
    """add_robot returns username = robotId, a fresh password the backend accepts, and the robot's own topics."""
    cred = registry.store.add_robot("agv-7")
    assert cred.username == cred.robot_id == "agv-7" and len(cred.password) >= 20
    assert cred.topics["pose"].endswith("/agv-7") and cred.topics["chunks"].endswith("/agv-7")
    assert registry.password_ok("agv-7", cred.password)
    assert registry.store.robots() == ["agv-7"]


def test_adding_twice_is_refused_and_rotate_replaces_the_password(registry) -> None:
    """A second add says to use --rotate; rotate gives a new password and the old one stops working."""
    first = registry.store.add_robot("agv-7")
    with pytest.raises((ValueError, EmqxError), match="--rotate"):
        registry.store.add_robot("agv-7")
    second = registry.store.add_robot("agv-7", rotate=True)
    assert second.password != first.password
    assert registry.password_ok("agv-7", second.password) and not registry.password_ok(
        "agv-7", first.password
    )


def test_remove_says_whether_there_was_a_robot(registry) -> None:
    """remove_robot is True once and False after; the robot is gone from the list."""
    registry.store.add_robot("a")
    registry.store.add_robot("b")
    assert registry.store.remove_robot("a") and not registry.store.remove_robot("a")
    assert registry.store.robots() == ["b"]


@pytest.mark.parametrize(
    "bad", ["mapservice-gateway", "mapservice-gateway-0", "mapservice-x", "a/b/c", "#", ""]
)
def test_service_names_and_bad_ids_are_refused(registry, bad) -> None:
    """The service's users, the reserved mapservice- prefix (gateways' client ids) and ids outside the robotId rule are never robots."""
    with pytest.raises(ValueError):
        registry.store.add_robot(bad)


def test_emqx_users_are_listed_across_pages(monkeypatch) -> None:
    """More users than a page: every page is read until hasnext is false."""
    monkeypatch.setattr(emqx_users, "PAGE", 2)
    reg = Registry("emqx", None)
    for i in range(5):
        reg.store.add_robot(f"r{i}")
    assert reg.store.robots() == [f"r{i}" for i in range(5)]
    assert [r.url.params["page"] for r in reg.fake.requests if r.method == "GET"] == ["1", "2", "3"]


def test_emqx_errors_say_what_to_do() -> None:
    """A wrong API key, an unreachable EMQX and missing settings each raise an EmqxError naming the setting to fix."""
    fake = FakeEmqx()
    wrong = EmqxUsers(
        "http://emqx:18083",
        KEY,
        "nope",
        client=httpx.Client(
            base_url="http://emqx:18083", transport=httpx.MockTransport(fake.handle)
        ),
    )
    with pytest.raises(EmqxError, match="MAPSERVICE_EMQX_API_KEY"):
        wrong.add_robot("r1")

    def refuse(request):
        raise httpx.ConnectError("connection refused", request=request)

    down = EmqxUsers(
        "http://emqx:18083",
        KEY,
        SECRET,
        client=httpx.Client(base_url="http://emqx:18083", transport=httpx.MockTransport(refuse)),
    )
    with pytest.raises(EmqxError, match="MAPSERVICE_EMQX_API_URL"):
        down.robots()
    with pytest.raises(EmqxError, match="MAPSERVICE_EMQX_API_SECRET"):
        EmqxUsers("http://emqx:18083", KEY, "")
    with pytest.raises(EmqxError, match="ConfigMap"):
        EmqxUsers(
            "http://emqx:18083",
            KEY,
            SECRET,
            client=httpx.Client(transport=httpx.MockTransport(fake.handle)),
        ).add_robot("r1", legacy_chunks=True)
