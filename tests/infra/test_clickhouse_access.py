"""The analysts' access to a ClickHouse server is one policy (mapservice/sql/server_access.py)
rendered for the Altinity operator and for a plain server's users.d (compose), each
rendering read back and compared with it; every setting of the profile is constant, and
the profile holds the limits the API applies to a statement."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import pytest

from mapservice.settings import Settings
from mapservice.sql import server_access
from mapservice.sql.allow_list import ALLOWED_SYSTEM_TABLES
from mapservice.sql.credentials import analyst_limits
from tests.infra.manifests import INFRA, PLATFORM, SECRET_REF, compose, load_all

USERS_D = INFRA / "clickhouse" / "users.d" / "analyst.xml"
REGENERATE = "python -m mapservice.sql.server_access > infra/clickhouse/users.d/analyst.xml"


def installation() -> dict:
    (chi,) = [
        d for d in load_all(PLATFORM / "clickhouse.yaml") if d["kind"] == "ClickHouseInstallation"
    ]
    return chi["spec"]["configuration"]


def test_the_operators_analyst_entries_are_the_policys() -> None:
    """Every users/profiles/quotas entry of the analyst in the installation, and no other."""
    configuration, policy = installation(), server_access.operator_configuration(Settings())
    for section, owner in (
        ("users", server_access.USER),
        ("profiles", server_access.PROFILE),
        ("quotas", server_access.QUOTA),
    ):
        entries = {k: v for k, v in configuration[section].items() if k.split("/")[0] == owner}
        assert entries == policy[section], section


def test_the_compose_servers_users_d_is_the_policys() -> None:
    assert USERS_D.read_text() == server_access.users_d(Settings()), f"regenerate: {REGENERATE}"


def read_users_d() -> tuple[dict[str, str], set[str], dict[str, str], ET.Element]:
    root = ET.parse(USERS_D).getroot()
    (profile,) = root.findall(f"profiles/{server_access.PROFILE}")
    settings = {e.tag: e.text or "" for e in profile if e.tag != "constraints"}
    constant = {e.tag for e in profile.findall("constraints/*") if e.find("const") is not None}
    (quota,) = root.findall(f"quotas/{server_access.QUOTA}/interval")
    (user,) = root.findall(f"users/{server_access.USER}")
    return settings, constant, {e.tag: e.text or "" for e in quota}, user


def test_the_users_d_file_read_back_is_read_only_constant_limited_and_granted_selects_only() -> (
    None
):
    settings, constant, quota, user = read_users_d()
    assert settings == {"readonly": "1", **analyst_limits(Settings()).settings()}
    assert constant == set(settings) | set(server_access.FILTERS)
    assert int(quota["duration"]) > 0 and all(int(v) > 0 for v in quota.values())
    assert user.findtext("profile") == server_access.PROFILE
    assert user.findtext("quota") == server_access.QUOTA
    grants = [q.text for q in user.findall("grants/query")]
    assert sorted(grants) == sorted(
        ["GRANT SELECT ON mapservice.*"]
        + [f"GRANT SELECT ON system.{t}" for t in ALLOWED_SYSTEM_TABLES]
    )
    (password,) = user.findall("password")
    assert (
        password.get("from_env") == server_access.PASSWORD_ENV and not (password.text or "").strip()
    )


@pytest.mark.parametrize(
    "env",
    [
        {},
        {"MAPSERVICE_ANALYST_MAX_EXECUTION_S": "7", "MAPSERVICE_ANALYST_MAX_THREADS": "3"},
        {
            "MAPSERVICE_ANALYST_MAX_RESULT_ROWS": "500",
            "MAPSERVICE_ANALYST_MAX_MEMORY_BYTES": str(128 * 1024**2),
        },
        {"MAPSERVICE_ANALYST_MAX_CONCURRENT_QUERIES": "4"},
    ],
)
def test_every_limit_the_api_applies_is_a_constant_of_the_profile_in_both_renderings(
    env: dict[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever the limits are set to: both renderings carry each of the API's limit
    settings with its value, each constant."""
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    settings = Settings()
    limits = analyst_limits(settings).settings()
    operator = server_access.operator_configuration(settings)["profiles"]
    root = ET.fromstring(server_access.users_d(settings).split("-->", 1)[1])
    (profile,) = root.findall(f"profiles/{server_access.PROFILE}")
    for name, value in {"readonly": "1", **limits}.items():
        assert (
            operator[f"analyst/{name}"] == value and f"analyst/constraints/{name}/const" in operator
        )
        assert (
            profile.findtext(name) == value
            and profile.find(f"constraints/{name}/const") is not None
        )


def test_compose_mounts_the_file_and_gives_the_server_and_the_api_the_analysts_password() -> None:
    services = compose()["services"]
    clickhouse, api = services["clickhouse"], services["api"]
    assert (
        "./clickhouse/users.d/analyst.xml:/etc/clickhouse-server/users.d/analyst.xml:ro"
        in clickhouse["volumes"]
    )
    server_ref = SECRET_REF.match(clickhouse["environment"][server_access.PASSWORD_ENV])
    api_ref = SECRET_REF.match(api["environment"]["MAPSERVICE_CLICKHOUSE_ANALYST_PASSWORD"])
    assert server_ref and api_ref and server_ref["var"] == api_ref["var"]
    assert api["environment"]["MAPSERVICE_CLICKHOUSE_ANALYST_USERNAME"] == server_access.USER
