"""EMQX's ACL file (`acl.conf` of the file authorizer), rendered from the access policy
(mqtt_policy.py), and the Kubernetes manifest that carries it.

EMQX reads the rules top to bottom, the first that matches decides, and the manifest sets
`authorization.no_match = deny` with a final `{deny, all}`. A robot's, a vehicle's and a
master control's rows name users by a regular expression over the username (which also keeps
wildcards and extra slashes out of `${username}`); the gateways subscribe only through their
shared subscription group on the internal listener, so their reads are `$share/<group>/...`.
A master control matches the robots' username rule too: its rows and a deny of everything
else come before the robots'. A robot allowed the 2019 chunk topic is added by hand in the
cluster (the rendered file says how), since the manifest names no robot.

`python -m mapservice.adapters.emqx_acl` rewrites the ConfigMap in
infra/k8s/platform/emqx.yaml from the policy; `--check` only says whether it is current.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterable
from pathlib import Path

from .mqtt_policy import (
    GATEWAY_USER,
    MASTER_PREFIX,
    MASTER_USERNAME,
    ME,
    PROCESSORS_USER,
    ROBOT_USERNAME,
    AclTopics,
    Action,
    Identity,
    Rule,
    access_policy,
    rules_of,
)

MANIFEST = Path("infra/k8s/platform/emqx.yaml")
# The gateways' MAPSERVICE_MQTT_SHARE_GROUP in infra/k8s/gateway.yaml.
SHARE_GROUP = "mapservice"
# EMQX's username rule for a vehicle: `<manufacturer>/<serialNumber>`, one slash.
VEHICLE_USERNAME = r"[^/+#:]{1,64}/[^/+#:]{1,64}"
_KEY = "  acl.conf: |\n"
_INDENT = "    "

_WHO = {
    Identity.GATEWAY: f'{{user, "{GATEWAY_USER}"}}',
    Identity.PROCESSORS: f'{{user, "{PROCESSORS_USER}"}}',
    Identity.EVERYONE: "all",
    Identity.MASTER: f'{{username, {{re, "^{MASTER_USERNAME}$"}}}}',
    Identity.ROBOT: f'{{username, {{re, "^{ROBOT_USERNAME}$"}}}}',
    Identity.VEHICLE: f'{{username, {{re, "^{VEHICLE_USERNAME}$"}}}}',
}


def _allow(identity: Identity, rules: Iterable[Rule], share_group: str) -> list[str]:
    lines = []
    for action in Action:
        topics = [r.topic_filter for r in rules if r.identity == identity and r.action == action]
        if identity == Identity.GATEWAY and action == Action.SUBSCRIBE:
            topics = [f"$share/{share_group}/{t}" for t in topics]
        if topics:
            quoted = ", ".join(f'"{t.replace(ME, "${username}")}"' for t in topics)
            lines.append(f"{{allow, {_WHO[identity]}, {action.value}, [{quoted}]}}.")
    return lines


def render_emqx_acl(topics: AclTopics, share_group: str = SHARE_GROUP) -> str:
    """The acl.conf text for these topics."""
    policy = access_policy(topics)
    legacy = rules_of(policy, Identity.LEGACY_CHUNKS)
    lines = [
        "%% Rendered from the access policy (mapservice/adapters/mqtt_policy.py) by",
        "%% `python -m mapservice.adapters.emqx_acl`: change the policy, not this file.",
        "%% The gateways read every robot message through the shared subscription and deliver",
        "%% the operators' commands (a vehicle's as instant actions).",
        *_allow(Identity.GATEWAY, policy, share_group),
        "%% The processors announce each change of the latest map and of the zones, and incidents.",
        *_allow(Identity.PROCESSORS, policy, share_group),
        "%% Every user learns of each change of the latest map and of the zones.",
        *_allow(Identity.EVERYONE, policy, share_group),
        "%% A VDA 5050 master control (`mapservice robot add --emqx mapservice-master-<name>`)",
        "%% sends orders and instant actions to every vehicle, reads all their messages and the",
        "%% incident alerts (the plant's systems);",
        "%% nothing else (its username also fits the robots' rule below).",
        *_allow(Identity.MASTER, policy, share_group),
        f'{{deny, {{username, {{re, "^{MASTER_PREFIX}"}}}}, all, ["#"]}}.',
        "%% A robot's username is its robotId (the gateway's robotId rule): it publishes only",
        "%% its own pose, chunks and command answers, and reads only its own commands.",
        *_allow(Identity.ROBOT, policy, share_group),
        "%% A VDA 5050 vehicle's username is <manufacturer>/<serialNumber>, the two levels of",
        "%% its topics: it publishes only in its own subtree and reads its own orders.",
        *_allow(Identity.VEHICLE, policy, share_group),
        "%% The 2019 chunk topic names no robot, so whoever may publish there may write chunks",
        "%% as any robotId: closed to robots. To let a robot that cannot be changed keep using",
        "%% it, allow it by name here (kubectl edit, then reload the file from the dashboard):",
        *(f'%%   {{allow, {{user, "<robotId>"}}, publish, ["{r.topic_filter}"]}}.' for r in legacy),
        "{deny, all}.",
    ]
    return "\n".join(lines) + "\n"


def acl_in_manifest(manifest_text: str) -> str:
    """The acl.conf a manifest's ConfigMap holds (its block, unindented)."""
    block = manifest_text.split(_KEY, 1)[1].split("\n---\n", 1)[0]
    return "".join(line.removeprefix(_INDENT) + "\n" for line in block.splitlines())


def with_acl(manifest_text: str, acl: str) -> str:
    """The manifest with its ConfigMap's acl.conf replaced by `acl`."""
    head, rest = manifest_text.split(_KEY, 1)
    tail = rest.split("\n---\n", 1)[1]
    block = "".join(_INDENT + line + "\n" for line in acl.splitlines())
    return f"{head}{_KEY}{block}---\n{tail}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m mapservice.adapters.emqx_acl",
        description="Render EMQX's ACL from the MQTT access policy into the EMQX manifest.",
    )
    parser.add_argument("manifest", nargs="?", type=Path, default=MANIFEST)
    parser.add_argument(
        "--check", action="store_true", help="exit 1 if the manifest is not the rendering"
    )
    args = parser.parse_args(argv)
    text = args.manifest.read_text()
    rendered = with_acl(text, render_emqx_acl(AclTopics()))
    if rendered == text:
        return 0
    if args.check:
        print(
            f"{args.manifest}: acl.conf differs from the access policy's rendering; run "
            "python -m mapservice.adapters.emqx_acl",
            file=sys.stderr,
        )
        return 1
    args.manifest.write_text(rendered)
    print(f"{args.manifest}: acl.conf rewritten from the access policy")
    return 0


if __name__ == "__main__":
    sys.exit(main())
