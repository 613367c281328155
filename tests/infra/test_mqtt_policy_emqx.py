"""EMQX's ACL in the platform manifest is the MQTT access policy's table: read back into rows
it is the same set, and evaluated as EMQX does (first match wins, then deny) it allows every
row's topics to their users and refuses every other user, action, topic and wildcard the
table does not allow."""

from __future__ import annotations

import re

import yaml

from mapservice.adapters import emqx_acl
from mapservice.adapters.mqtt_policy import (
    GATEWAY_USER,
    ME,
    PROCESSORS_USER,
    AclTopics,
    Action,
    Identity,
    Rule,
    access_policy,
)
from tests.fixtures.emqx_acl_eval import RULE, emqx_allows, rule_lines, rule_topics
from tests.fixtures.mqtt_policy_cases import (
    MASTER,
    ODD_USERNAMES,
    ROBOTS,
    VEHICLES,
    allowing_rows,
    concrete_topics,
    fleet,
    wildcard_filters,
)
from tests.fixtures.paths import ROOT

MANIFEST = ROOT / "infra/k8s/platform/emqx.yaml"
TOPICS = AclTopics()
POLICY = access_policy(TOPICS)
# The manifest names no robot allowed the 2019 chunk topic (added by hand in the cluster).
EMQX_POLICY = tuple(r for r in POLICY if r.identity != Identity.LEGACY_CHUNKS)
SHARED = f"$share/{emqx_acl.SHARE_GROUP}/"


def manifest_rules() -> list[str]:
    (config_map,) = [
        d
        for d in yaml.safe_load_all(MANIFEST.read_text())
        if d and d["kind"] == "ConfigMap" and d["metadata"]["name"] == "mapservice-emqx-acl"
    ]
    return rule_lines(config_map["data"]["acl.conf"])


def identity_of(rule: re.Match[str]) -> Identity:
    """Whom a rule names, told by the usernames it matches."""
    if rule["who"] == "all":
        return Identity.EVERYONE
    if rule["user"]:
        return {GATEWAY_USER: Identity.GATEWAY, PROCESSORS_USER: Identity.PROCESSORS}[rule["user"]]
    matches = {name for name in (ROBOTS[0], VEHICLES[0], MASTER) if re.search(rule["re"], name)}
    if VEHICLES[0] in matches:
        return Identity.VEHICLE
    return Identity.ROBOT if ROBOTS[0] in matches else Identity.MASTER


def rows_of(rules: list[str]) -> set[Rule]:
    """The allow rules as rows of the table (`${username}` as `{me}`, the gateways' share
    group taken off their subscriptions)."""
    rows = set()
    for line in rules:
        m = RULE.match(line)
        if not m or m["perm"] != "allow":
            continue
        identity = identity_of(m)
        for topic in rule_topics(m):
            if identity == Identity.GATEWAY and m["action"] == "subscribe":
                assert topic.startswith(SHARED), f"the gateways subscribe only shared: {topic}"
                topic = topic.removeprefix(SHARED)
            rows.add(Rule(identity, Action(m["action"]), topic.replace("${username}", ME)))
    return rows


def test_the_emqx_rules_read_back_as_the_access_policy() -> None:
    """Same allowed set: nothing in the table missing on EMQX, nothing more on EMQX."""
    rows = rows_of(manifest_rules())
    missing = sorted(set(EMQX_POLICY) - rows, key=str)
    extra = sorted(rows - set(EMQX_POLICY), key=str)
    assert not missing and not extra, f"missing on EMQX: {missing}; not in the table: {extra}"


def test_emqx_allows_each_row_and_refuses_every_other_combination() -> None:
    users = {**fleet(legacy=False), **{u: frozenset({Identity.EVERYONE}) for u in ODD_USERNAMES}}
    rules = manifest_rules()
    concrete = concrete_topics(EMQX_POLICY, users, TOPICS)
    spies = wildcard_filters(concrete)
    wrong, used, allowed, refused = [], set(), 0, 0
    for username, kinds in users.items():
        cases = [(Action.PUBLISH, t) for t in concrete]
        cases += [(Action.SUBSCRIBE, t) for t in (*concrete, *spies)]
        for action, topic in cases:
            rows = allowing_rows(EMQX_POLICY, kinds, username, action, topic)
            # The gateways subscribe through their share group (and, as every user, directly).
            asked = [topic]
            if username == GATEWAY_USER and action == Action.SUBSCRIBE:
                asked.append(SHARED + topic)
            answer = any(emqx_allows(rules, username, action.value, t) for t in asked)
            if answer != bool(rows):
                wrong.append((username, action.value, topic, "allowed" if answer else "refused"))
            used.update(rows)
            allowed, refused = allowed + bool(rows), refused + (not rows)
    assert wrong == [], f"{len(wrong)} answers differ from the table, e.g. {wrong[:10]}"
    assert used == set(EMQX_POLICY), f"rows no case exercised: {set(EMQX_POLICY) - used}"
    assert allowed > 100 and refused > 10 * allowed, (allowed, refused)


def test_the_manifest_holds_the_rendering_of_the_policy() -> None:
    """`python -m mapservice.adapters.emqx_acl --check` passes on the checked-in manifest,
    and the gateways' share group is the one the manifest's rules name."""
    text = MANIFEST.read_text()
    assert emqx_acl.acl_in_manifest(text) == emqx_acl.render_emqx_acl(TOPICS)
    assert emqx_acl.main([str(MANIFEST), "--check"]) == 0
    gateway = (ROOT / "infra/k8s/gateway.yaml").read_text()
    assert re.search(
        rf"MAPSERVICE_MQTT_SHARE_GROUP\n\s+value: {re.escape(emqx_acl.SHARE_GROUP)}\n", gateway
    )


def test_the_regenerate_command_rewrites_a_drifted_manifest(tmp_path) -> None:
    drifted = tmp_path / "emqx.yaml"
    text = MANIFEST.read_text()
    drifted.write_text(text.replace(f', "{TOPICS.zone_advertisement_topic}"', ""))
    assert emqx_acl.main([str(drifted), "--check"]) == 1
    assert emqx_acl.main([str(drifted)]) == 0
    assert drifted.read_text() == text
