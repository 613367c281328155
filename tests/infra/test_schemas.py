"""Every Kubernetes manifest in infra/ validates offline, and the platform files agree with the code.

Core kinds are checked with `kubernetes-validate` (the Kubernetes OpenAPI schemas it
bundles, strict: an unknown field is an error). Operator kinds (Strimzi, EMQX Operator,
Altinity ClickHouse Operator) are checked against the CRD schemas vendored in
`tests/infra/crds/` (see its README for their source), made strict the same way: where a
CRD schema lists an object's properties and neither preserves unknown fields nor allows
additional ones, any other field is an error, as `kubectl apply --validate=strict` would say.
Whether the platform's resources agree with the code is in test_platform.py.
"""

from __future__ import annotations

import copy
import json
import re
import shutil
import subprocess
from functools import cache
from pathlib import Path

import jsonschema
import kubernetes_validate
import pytest
import yaml

from tests.fixtures.paths import ROOT
from tests.infra.manifests import k8s_objects

CRDS = Path(__file__).parent / "crds"
KUBERNETES_VERSION = "1.33.0"


def strict(schema: dict) -> dict:
    """The CRD schema with unknown fields refused wherever the CRD itself does not allow them."""
    schema = copy.deepcopy(schema)

    def walk(node):
        if isinstance(node, dict):
            # Kubernetes evaluates patterns with Go's RE2; the few Python cannot compile
            # (e.g. EMQX's `[a-zA-Z\\d-_]`) are left unchecked rather than misread.
            if isinstance(node.get("pattern"), str):
                try:
                    re.compile(node["pattern"])
                except re.error:
                    del node["pattern"]
            if (
                "properties" in node
                and "additionalProperties" not in node
                and not node.get("x-kubernetes-preserve-unknown-fields")
            ):
                node["additionalProperties"] = False
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(schema)
    # Every object carries these, which CRD schemas leave out or declare loosely.
    schema.setdefault("properties", {})
    for field in ("apiVersion", "kind", "metadata"):
        schema["properties"].setdefault(field, {})
    schema["properties"]["metadata"] = {"type": "object"}
    return schema


@cache
def crd_schemas() -> dict[tuple[str, str], dict]:
    """(apiVersion, kind) -> strict schema, from the vendored CRDs."""
    out = {}
    for path in CRDS.glob("*.json"):
        crd = json.loads(path.read_text())
        out[(crd["apiVersion"], crd["kind"])] = strict(crd["schema"])
    return out


def validate(doc: dict) -> None:
    """Raises when `doc` does not validate against its kind's schema."""
    key = (doc["apiVersion"], doc["kind"])
    if key in crd_schemas():
        jsonschema.Draft4Validator(crd_schemas()[key]).validate(doc)
    else:
        kubernetes_validate.validate(doc, KUBERNETES_VERSION, strict=True)


@pytest.mark.parametrize(
    ("path", "doc"),
    k8s_objects(),
    ids=lambda v: (
        v.name
        if isinstance(v, Path)
        else v.get("kind", "?") + "/" + v["metadata"]["name"]
        if isinstance(v, dict)
        else str(v)
    ),
)
def test_manifest_validates_against_its_schema(path: Path, doc: dict) -> None:
    """Each object validates strictly against the Kubernetes or operator CRD schema of its kind."""
    validate(doc)


def test_every_operator_kind_has_a_vendored_schema() -> None:
    """Every non-core kind used in infra/k8s has a CRD schema in tests/infra/crds (none goes unchecked)."""
    core_groups = (
        "v1",
        "apps/",
        "batch/",
        "policy/",
        "networking.k8s.io/",
        "autoscaling/",
        "rbac.authorization.k8s.io/",
    )
    used = {
        (d["apiVersion"], d["kind"])
        for _, d in k8s_objects()
        if not d["apiVersion"].startswith(core_groups)
    }
    assert used, "the platform files use operator kinds"
    assert used <= set(crd_schemas()), used - set(crd_schemas())


def test_the_validation_refuses_an_unknown_field() -> None:
    """A misspelt field fails both validators (the checks above can fail)."""
    deployment = next(d for _, d in k8s_objects() if d["kind"] == "Deployment")
    bad = copy.deepcopy(deployment)
    bad["spec"]["replica"] = 2
    with pytest.raises(kubernetes_validate.ValidationError):
        validate(bad)
    emqx = next(d for _, d in k8s_objects() if d["kind"] == "EMQX")
    bad = copy.deepcopy(emqx)
    bad["spec"]["coreTemplate"]["spec"]["replica"] = 3
    with pytest.raises(jsonschema.ValidationError):
        validate(bad)


def test_production_overlay_pins_the_image_by_digest() -> None:
    """The production overlay names the image by sha256 digest, never by tag alone."""
    overlay = yaml.safe_load(
        (ROOT / "infra" / "overlays" / "production" / "kustomization.yaml").read_text()
    )
    (image,) = [i for i in overlay["images"] if i["name"] == "mapservice"]
    assert re.fullmatch(r"sha256:[0-9a-f]{64}", image["digest"])
    assert "newTag" not in image


@pytest.mark.skipif(shutil.which("kubectl") is None, reason="kubectl is not installed")
def test_production_overlay_renders_with_the_digest() -> None:
    """kubectl kustomize renders the overlay, and every mapservice container uses the digest."""
    out = subprocess.run(
        ["kubectl", "kustomize", str(ROOT / "infra" / "overlays" / "production")],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    images = re.findall(r"image: (\S+)", out)
    assert images and all("@sha256:" in i for i in images if "mapservice" in i)


def test_pods_run_without_a_service_account_token() -> None:
    """Every mapservice pod uses the mapservice ServiceAccount and mounts no API token."""
    workloads = [d for _, d in k8s_objects() if d["kind"] in ("Deployment", "StatefulSet", "Job")]
    assert {w["metadata"]["name"] for w in workloads} >= {
        "mapservice-gateway",
        "mapservice-api",
        "mapservice-processors",
    }
    for w in workloads:
        spec = w["spec"]["template"]["spec"]
        assert spec["serviceAccountName"] == "mapservice", w["metadata"]["name"]
        assert spec["automountServiceAccountToken"] is False, w["metadata"]["name"]


def test_network_policies_deny_by_default_and_allow_the_dependencies() -> None:
    """A default-deny policy selects every pod; egress reaches each dependency's port from the ConfigMap."""
    policies = [d for _, d in k8s_objects() if d["kind"] == "NetworkPolicy"]
    deny = [
        p
        for p in policies
        if p["spec"]["podSelector"] == {}
        and set(p["spec"]["policyTypes"]) == {"Ingress", "Egress"}
        and not p["spec"].get("ingress")
        and not p["spec"].get("egress")
    ]
    assert deny
    config = next(
        d
        for _, d in k8s_objects()
        if d["kind"] == "ConfigMap" and d["metadata"]["name"] == "mapservice"
    )["data"]
    ports = {
        int(config["MAPSERVICE_KAFKA_BOOTSTRAP"].rsplit(":", 1)[1]),
        int(config["MAPSERVICE_CLICKHOUSE_DSN"].rsplit(":", 1)[1]),
        int(config["MAPSERVICE_MQTT_URL"].rsplit(":", 1)[1]),
        53,
    }
    allowed = {
        p["port"]
        for pol in policies
        for rule in pol["spec"].get("egress", [])
        for p in rule.get("ports", [])
    }
    assert ports <= allowed, ports - allowed
