"""What the API says about who may open a scope matches what it checks: the refusals'
wording (WHO_MAY), the settings' descriptions and the OpenAPI bearer scheme name exactly
the roles that GRANTS gives the scope."""

from __future__ import annotations

import re

import pytest

from mapservice.api.access_guard import DOCS_ROLES
from mapservice.api.credentials import GRANTS, ROLE_SETTINGS, WHO_MAY, Scope
from mapservice.settings import Settings
from tests.api.access_kit import app_for, settings_for

ROLE_WORD = re.compile(r"\b(" + "|".join(GRANTS) + r")\b")  # lower case: not in setting names
SETTING_WORD = re.compile(r"\bMAPSERVICE_[A-Z_]+\b")


def roles_named(text: str) -> set[str]:
    return set(ROLE_WORD.findall(text))


def holding(scope: Scope) -> set[str]:
    return {role for role, scopes in GRANTS.items() if scope in scopes}


@pytest.mark.parametrize("scope", [s for s in Scope if s is not Scope.PUBLIC])
def test_who_may_names_exactly_the_roles_that_hold_each_scope(scope: Scope) -> None:
    text = WHO_MAY[scope]
    assert roles_named(text) == holding(scope), text
    assert set(SETTING_WORD.findall(text)) == {ROLE_SETTINGS[r] for r in holding(scope)}, text


def test_no_role_holds_the_public_scope_and_every_role_has_its_setting() -> None:
    assert holding(Scope.PUBLIC) == set()
    assert set(ROLE_SETTINGS) == set(GRANTS)
    fields = set(Settings.model_fields)
    for setting in ROLE_SETTINGS.values():
        assert setting.removeprefix("MAPSERVICE_").lower() in fields, setting


def test_the_settings_descriptions_name_the_roles_that_are_let_in() -> None:
    read = Settings.model_fields["api_read_access"].description or ""
    assert roles_named(read.split("`token`", 1)[1]) == holding(Scope.READ), read
    docs = Settings.model_fields["api_docs_access"].description or ""
    assert roles_named(docs) == set(DOCS_ROLES), docs


def test_the_openapi_bearer_scheme_names_every_role() -> None:
    schema = app_for(settings_for("token")).openapi()
    description = schema["components"]["securitySchemes"]["bearer"]["description"]
    assert roles_named(description) == set(GRANTS), description
