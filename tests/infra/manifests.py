"""The deployment files in infra/ as the tests read them: compose services, Kubernetes
documents and containers, the environment each process would see (secrets given dummy
values), and the Settings that environment loads."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from pydantic import SecretStr

from mapservice.settings import Settings
from tests.fixtures.paths import ROOT

INFRA = ROOT / "infra"
K8S = INFRA / "k8s"
COMPOSE = INFRA / "compose.yaml"
DOCKERFILE = INFRA / "Dockerfile"
MOSQUITTO_CONF = INFRA / "mosquitto" / "mosquitto.conf"
INFRA_README = INFRA / "README.md"
DOCKERIGNORE = ROOT / ".dockerignore"
STRIMZI_TOPICS = K8S / "strimzi-topics.yaml"
KUSTOMIZATION = K8S / "kustomization.yaml"
PLATFORM = K8S / "platform"  # the operators' custom resources: Kafka, EMQX, ClickHouse

COMPONENTS = {"gateway", "processors", "api"}
ONE_SHOT = {"migrate"}  # runs to completion once per release
SETTINGS_VARS = {f"MAPSERVICE_{name.upper()}" for name in Settings.model_fields}
# Fields typed SecretStr: admin token and the passwords.
SECRET_VARS = {
    f"MAPSERVICE_{name.upper()}"
    for name, field in Settings.model_fields.items()
    if "SecretStr" in str(field.annotation) or field.annotation is SecretStr
}
# Values used where the real secret is supplied at deploy time.
DUMMY_SECRET = "0123456789abcdef0123456789abcdef"


def dummy_secret(key: str) -> str:
    """The dummy value of a Secret key, in the shape its setting takes."""
    return f"agv-1={DUMMY_SECRET}" if key == "MAPSERVICE_API_ROBOT_TOKENS" else DUMMY_SECRET


SECRET_REF = re.compile(r"^\$\{(?P<var>[A-Za-z_][A-Za-z0-9_]*):\?(?P<msg>[^}]+)\}$")
VAR_NAME = re.compile(r"\bMAPSERVICE_[A-Z0-9_]*[A-Z0-9]\b")


def is_secret_name(name: str) -> bool:
    upper = name.upper()
    return upper in SECRET_VARS or upper.endswith(("_PASSWORD", "_TOKEN", "_SECRET"))


# ---------------------------------------------------------------------------- loading


def yaml_files() -> list[Path]:
    return sorted(p for p in INFRA.rglob("*") if p.suffix in (".yaml", ".yml") and p.is_file())


def load_all(path: Path) -> list:
    return [doc for doc in yaml.safe_load_all(path.read_text()) if doc is not None]


def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def compose_mapservice() -> dict[str, dict]:
    """Compose services that run the mapservice image, by service name."""
    return {
        name: svc
        for name, svc in compose()["services"].items()
        if "build" in svc or str(svc.get("image", "")).startswith("mapservice")
    }


def compose_components() -> dict[str, dict]:
    """The long-running ones (not the one-shot migrate)."""
    return {name: svc for name, svc in compose_mapservice().items() if name not in ONE_SHOT}


def kustomize_resources() -> list[str]:
    return yaml.safe_load(KUSTOMIZATION.read_text())["resources"]


def k8s_docs() -> list[dict]:
    """Every document of the manifests kustomization.yaml deploys."""
    return [doc for name in kustomize_resources() for doc in load_all(K8S / name)]


def k8s_objects() -> list[tuple[Path, dict]]:
    """Every Kubernetes object in infra/k8s (recursively), with its file."""
    found = []
    for path in sorted(K8S.rglob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc and "kind" in doc and doc.get("apiVersion") != "kustomize.config.k8s.io/v1beta1":
                found.append((path, doc))
    return found


def jobs() -> list[tuple[dict, dict]]:
    """(job, container) for every container of a Job."""
    return [
        (doc, c)
        for doc in k8s_docs()
        if doc["kind"] == "Job"
        for c in doc["spec"]["template"]["spec"]["containers"]
    ]


def workloads() -> list[tuple[dict, dict]]:
    """(workload, container) for every container of a Deployment or StatefulSet."""
    return [
        (doc, c)
        for doc in k8s_docs()
        if doc["kind"] in ("Deployment", "StatefulSet")
        for c in doc["spec"]["template"]["spec"]["containers"]
    ]


def configmap(name: str) -> dict[str, str]:
    for doc in k8s_docs():
        if doc["kind"] == "ConfigMap" and doc["metadata"]["name"] == name:
            return doc.get("data", {})
    raise AssertionError(f"no ConfigMap {name!r} in {kustomize_resources()}")


def container_argv(container: dict) -> list[str]:
    """The arguments after `mapservice` (the image's entrypoint, or an explicit command)."""
    command = list(container.get("command", []))
    if command:
        assert Path(command[0]).name == "mapservice", f"{container['name']}: command {command}"
        return command[1:] + list(container.get("args", []))
    return list(container.get("args", []))


def health_port(argv: list[str]) -> int | None:
    if "--health-port" in argv:
        return int(argv[argv.index("--health-port") + 1])
    return None


def secret_keys_from_readme() -> set[str]:
    """Keys of the documented `kubectl create secret generic mapservice ...` command."""
    text = INFRA_README.read_text().replace("\\\n", " ")
    commands = [
        line
        for line in text.splitlines()
        if "kubectl" in line and "create secret generic mapservice" in line
    ]
    assert commands, "infra/README.md documents no `kubectl create secret generic mapservice`"
    return set(re.findall(r"--from-literal=([A-Z0-9_]+)=", " ".join(commands)))


def k8s_env(workload: dict, container: dict) -> dict[str, str]:
    """What the container's process would see: ConfigMap, Secret (dummy values), env."""
    env: dict[str, str] = {}
    for source in container.get("envFrom", []):
        if "configMapRef" in source:
            env.update(configmap(source["configMapRef"]["name"]))
        if "secretRef" in source:
            env.update({key: dummy_secret(key) for key in secret_keys_from_readme()})
    pod_name = f"{workload['metadata']['name']}-0"
    for entry in container.get("env", []):
        if "value" in entry:
            env[entry["name"]] = str(entry["value"])
        elif entry.get("valueFrom", {}).get("fieldRef", {}).get("fieldPath") == "metadata.name":
            env[entry["name"]] = pod_name
        elif "secretKeyRef" in entry.get("valueFrom", {}):
            env[entry["name"]] = DUMMY_SECRET
    return env


def compose_env(service: dict) -> dict[str, str]:
    """The service's environment with every ${VAR:?...} given a value, as compose would."""
    raw = service.get("environment", {})
    if isinstance(raw, list):
        raw = dict(item.split("=", 1) for item in raw)
    return {key: SECRET_REF.sub(DUMMY_SECRET, str(value)) for key, value in raw.items()}


def settings_from(env: dict[str, str]) -> Settings:
    with pytest.MonkeyPatch.context() as mp:
        for key, value in env.items():
            mp.setenv(key, value)
        return Settings()
