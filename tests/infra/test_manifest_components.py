"""Each component as infra/ deploys it: its probes and scrape annotations answered by the
handlers it really runs, the settings its environment gives (production, listening on
all interfaces, guarded metrics), its topics, migrations and ClickHouse cluster."""

from __future__ import annotations

import re
import urllib.error
import urllib.request

import pytest

from mapservice.adapters.kafka_topics import topic_config, topic_partitions
from mapservice.settings import Settings
from tests.infra.manifests import (
    DUMMY_SECRET,
    K8S,
    STRIMZI_TOPICS,
    compose,
    compose_components,
    compose_env,
    configmap,
    container_argv,
    health_port,
    jobs,
    k8s_docs,
    k8s_env,
    load_all,
    secret_keys_from_readme,
    settings_from,
    workloads,
)

# ------------------------------------------------------------- the real health handlers


@pytest.fixture(scope="module")
def served():
    """served(component, path) -> HTTP status from the handler the component really runs."""
    from fastapi.testclient import TestClient

    from mapservice.api.app import create_app
    from mapservice.runtime.health_server import serve_health
    from mapservice.testing.memory_store import MemoryStore

    health = serve_health("127.0.0.1", 0, lambda: {"ok": True})
    port = health.server_address[1]
    # By the pod's address, as the kubelet and Prometheus ask (no host name to check).
    api = TestClient(
        create_app(Settings(), MemoryStore(), {"clickhouse": lambda: True}),
        base_url="http://10.0.0.7",
    )

    def status(component: str, path: str) -> int:
        if component == "api":
            return api.get(path).status_code
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as resp:
                return resp.status
        except urllib.error.HTTPError as exc:
            return exc.code

    yield status
    health.shutdown()
    health.server_close()


def test_gateway_statefulset_takes_its_mqtt_client_id_from_the_pod_name():
    """The gateway is a 2-replica StatefulSet sharing `$share/mapservice/`, client id = pod name."""
    gateways = [(w, c) for w, c in workloads() if container_argv(c)[:1] == ["gateway"]]
    assert len(gateways) == 1
    workload, container = gateways[0]
    assert workload["kind"] == "StatefulSet"
    assert workload["spec"]["replicas"] == 2
    env = {e["name"]: e for e in container["env"]}
    assert env["MAPSERVICE_MQTT_CLIENT_ID"]["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.name"
    assert env["MAPSERVICE_MQTT_SHARE_GROUP"]["value"] == "mapservice"
    settings = settings_from(k8s_env(workload, container))
    assert settings.mqtt_client_id == f"{workload['metadata']['name']}-0"
    assert all(t.startswith("$share/mapservice/") for t in settings.mqtt_subscriptions)
    # compose runs one gateway with a fixed id of its own (not the default).
    gateway = compose_components()["gateway"]
    assert compose_env(gateway)["MAPSERVICE_MQTT_CLIENT_ID"] != Settings().mqtt_client_id
    assert "deploy" not in gateway or gateway["deploy"].get("replicas", 1) == 1


def probes(container: dict) -> dict[str, dict]:
    return {
        kind: container[kind]["httpGet"]
        for kind in ("startupProbe", "livenessProbe", "readinessProbe")
        if kind in container
    }


def resolve_port(container: dict, port) -> int:
    if isinstance(port, int):
        return port
    for p in container.get("ports", []):
        if p.get("name") == port:
            return p["containerPort"]
    raise AssertionError(f"{container['name']}: no container port named {port!r}")


def listen_port(component: str, argv: list[str], env: dict[str, str]) -> int:
    if component == "api":
        return settings_from(env).api_port
    port = health_port(argv)
    assert port is not None, f"{component} runs without --health-port: nothing to probe"
    return port


def test_probes_point_at_paths_and_ports_the_components_serve(served):
    """Probes, scrape annotations and healthchecks hit paths the real handlers answer 200, on the right port."""
    checked = 0
    for workload, container in workloads():
        argv = container_argv(container)
        component = argv[0]
        port = listen_port(component, argv, k8s_env(workload, container))
        found = probes(container)
        assert {"livenessProbe", "readinessProbe"} <= found.keys(), workload["metadata"]["name"]
        for kind, get in found.items():
            assert resolve_port(container, get["port"]) == port, (component, kind)
            assert served(component, get["path"]) == 200, (component, kind, get["path"])
            checked += 1
        assert found["livenessProbe"]["path"] == "/healthz"
        assert found["readinessProbe"]["path"] == "/readyz"
        notes = workload["spec"]["template"]["metadata"]["annotations"]
        assert notes["prometheus.io/scrape"] == "true"
        assert int(notes["prometheus.io/port"]) == port
        assert served(component, notes["prometheus.io/path"]) == 200
        resources = container["resources"]
        assert {"cpu", "memory"} <= resources["requests"].keys() <= resources["limits"].keys()
    for name, svc in compose_components().items():
        argv = [str(a) for a in svc["command"]]
        test = " ".join(str(part) for part in svc["healthcheck"]["test"])
        match = re.search(r"http://(?:127\.0\.0\.1|localhost):(\d+)(/[A-Za-z0-9_/-]*)", test)
        assert match, f"compose {name}: healthcheck is not an HTTP check: {test}"
        assert int(match.group(1)) == listen_port(argv[0], argv, compose_env(svc)), name
        assert match.group(2) == "/readyz", name
        assert served(argv[0], match.group(2)) == 200
        checked += 1
    assert checked >= 3 * 3 + 3
    # The handlers really distinguish: a path they do not serve is not 200.
    assert served("gateway", "/livez") != 200
    assert served("api", "/no-such-path") != 200


def test_the_api_as_deployed_guards_metrics_and_docs_but_not_probes():
    """With the k8s ConfigMap and Secret, the API's probes answer without a token, /metrics and
    /openapi.json only with one, and the PodMonitor scrapes with the Secret's metrics token."""
    from fastapi.testclient import TestClient

    from mapservice.api.app import create_app
    from mapservice.testing.memory_store import MemoryStore

    [(workload, container)] = [(w, c) for w, c in workloads() if container_argv(c)[:1] == ["api"]]
    settings = settings_from(k8s_env(workload, container))
    assert (settings.metrics_access, settings.docs_access, settings.api_read_access) == (
        "token",
        "token",
        "open",
    )
    # By the pod's address, as the kubelet and Prometheus ask.
    api = TestClient(
        create_app(settings, MemoryStore(), {"clickhouse": lambda: True}),
        base_url="http://10.0.0.7",
    )
    for kind, get in probes(container).items():
        assert api.get(get["path"]).status_code == 200, kind
    token = {"Authorization": f"Bearer {DUMMY_SECRET}"}  # every Secret key holds it here
    for path in ("/metrics", "/openapi.json"):
        assert api.get(path).status_code == 401, path
        assert api.get(path, headers=token).status_code == 200, path
    [monitor] = load_all(K8S / "monitoring" / "podmonitor.yaml")
    [http] = [e for e in monitor["spec"]["podMetricsEndpoints"] if e["port"] == "http"]
    assert http["authorization"] == {
        "type": "Bearer",
        "credentials": {"name": "mapservice", "key": "MAPSERVICE_API_METRICS_TOKEN"},
    }
    assert "MAPSERVICE_API_METRICS_TOKEN" in secret_keys_from_readme()


def test_probed_components_listen_on_all_interfaces():
    """Everything probed binds 0.0.0.0 (MAPSERVICE_API_HOST also binds the health servers)."""
    for workload, container in workloads():
        settings = settings_from(k8s_env(workload, container))
        assert settings.api_host == "0.0.0.0", workload["metadata"]["name"]
    for name, svc in compose_components().items():
        assert settings_from(compose_env(svc)).api_host == "0.0.0.0", name


def test_each_component_environment_gives_valid_production_settings():
    """Each component's env loads as production Settings (server DSN, rebalance >= 10 s), not without its token."""
    envs = [(f"compose:{n}", compose_env(s)) for n, s in compose_components().items()]
    envs += [(f"k8s:{w['metadata']['name']}", k8s_env(w, c)) for w, c in workloads()]
    assert len(envs) == 6
    for where, env in envs:
        settings = settings_from(env)
        assert settings.mode == "production", where
        assert settings.resolved_clickhouse_dsn.startswith(("http://", "https://")), where
        assert settings.kafka_rebalance_timeout_s >= 10, where
        assert settings.admin_token.get_secret_value() == DUMMY_SECRET, where
        assert settings.clickhouse_password.get_secret_value() == DUMMY_SECRET, where
        without_token = {k: v for k, v in env.items() if k != "MAPSERVICE_ADMIN_TOKEN"}
        with pytest.raises(ValueError, match="ADMIN_TOKEN"):
            settings_from(without_token)
    assert (
        compose_env(compose()["services"]["gateway"])["MAPSERVICE_CLICKHOUSE_DSN"]
        == "http://clickhouse:8123"
    )


def test_strimzi_topics_match_the_settings():
    """strimzi-topics.yaml has the five Settings topics, ConfigMap partitions/replicas, and
    exactly the configs the service creates topics with (mapservice.adapters.kafka_topics.topic_config):
    retention as the history's, meta compacted x1, live x1 with the live retention."""
    settings = settings_from(
        {
            **configmap("mapservice"),
            "MAPSERVICE_ADMIN_TOKEN": DUMMY_SECRET,
            "MAPSERVICE_CLICKHOUSE_PASSWORD": DUMMY_SECRET,
        }
    )
    docs = load_all(STRIMZI_TOPICS)
    assert all(
        d["kind"] == "KafkaTopic" and d["apiVersion"].startswith("kafka.strimzi.io/") for d in docs
    )
    topics = {d["spec"].get("topicName", d["metadata"]["name"]): d for d in docs}
    assert sorted(topics) == sorted(settings.kafka_topics)
    for name, doc in topics.items():
        spec = doc["spec"]
        meta = name in (settings.topic_meta_events, settings.topic_annotation_events)
        assert spec["partitions"] == topic_partitions(settings, name), name
        if name == settings.topic_live:
            assert spec["config"]["retention.ms"] == settings.live_retention_s * 1000
        assert spec["replicas"] == settings.kafka_replication, name
        assert spec.get("config", {}).get("cleanup.policy", "delete") == (
            "compact" if meta else "delete"
        ), name
        assert {k: str(v) for k, v in spec.get("config", {}).items()} == topic_config(
            settings, name
        ), name
        cluster = doc["metadata"]["labels"]["strimzi.io/cluster"]
        assert settings.kafka_bootstrap.startswith(f"{cluster}-kafka-bootstrap."), name


def test_migrations_run_once_per_release_before_the_components():
    """A k8s Job named after the schema version and a compose one-shot run `mapservice migrate`
    in production mode; compose's processors and API start only after it succeeded."""
    from mapservice.adapters.clickhouse.schema import SCHEMA_VERSION

    ((job, container),) = jobs()
    assert job["metadata"]["name"] == f"mapservice-migrate-v{SCHEMA_VERSION}"
    assert container_argv(container) == ["migrate"]
    assert job["spec"]["template"]["spec"]["restartPolicy"] in ("OnFailure", "Never")
    compose_migrate = compose()["services"]["migrate"]
    assert compose_migrate["command"] == ["migrate"] and compose_migrate["restart"] == "no"
    for where, env in (("k8s", k8s_env(job, container)), ("compose", compose_env(compose_migrate))):
        settings = settings_from(env)
        assert settings.mode == "production" and not settings.migrates_on_start, where
    for name in ("processors", "api"):
        assert compose()["services"][name]["depends_on"]["migrate"] == {
            "condition": "service_completed_successfully"
        }, name
    for workload, container in workloads():  # nobody else migrates in production mode
        assert not settings_from(k8s_env(workload, container)).migrates_on_start


def test_the_schema_cluster_is_the_installations_replicated_cluster():
    """MAPSERVICE_CLICKHOUSE_CLUSTER names a cluster of the ClickHouseInstallation that has
    two or more replicas and a Keeper (what Replicated tables ON CLUSTER need)."""
    (chi,) = [
        d
        for d in load_all(K8S / "platform" / "clickhouse.yaml")
        if d["kind"] == "ClickHouseInstallation"
    ]
    clusters = {c["name"]: c["layout"] for c in chi["spec"]["configuration"]["clusters"]}
    name = configmap("mapservice")["MAPSERVICE_CLICKHOUSE_CLUSTER"]
    assert name in clusters and clusters[name]["replicasCount"] >= 2
    assert chi["spec"]["configuration"]["zookeeper"]["nodes"]
    host = settings_from(
        {
            **configmap("mapservice"),
            "MAPSERVICE_ADMIN_TOKEN": DUMMY_SECRET,
            "MAPSERVICE_CLICKHOUSE_PASSWORD": DUMMY_SECRET,
        }
    ).resolved_clickhouse_dsn
    assert f"clickhouse-{chi['metadata']['name']}." in host  # the operator's Service for the CHI


def test_every_ingress_host_is_a_name_the_api_pods_answer_and_reaches_a_port_they_serve():
    """The API's HTTP and its Foxglove port each have an ingress; every routed host is one
    the pods answer (a host they do not know gets a 421 from the API and the Foxglove gate
    alike), with TLS for it; every backend is a port of the Service."""
    from mapservice.api.limits import allowed_hosts, host_allowed

    [(api, container)] = [
        (w, c) for w, c in workloads() if w["metadata"]["name"] == "mapservice-api"
    ]
    allowed = allowed_hosts(settings_from(k8s_env(api, container)))
    ports = {
        doc["metadata"]["name"]: {p["name"] for p in doc["spec"]["ports"]}
        for doc in k8s_docs()
        if doc["kind"] == "Service"
    }
    routed = set()
    for ingress in (doc for doc in k8s_docs() if doc["kind"] == "Ingress"):
        tls_hosts = {h for t in ingress["spec"].get("tls", []) for h in t["hosts"]}
        for rule in ingress["spec"]["rules"]:
            assert host_allowed(rule["host"], allowed), (ingress["metadata"]["name"], allowed)
            assert rule["host"] in tls_hosts, ingress["metadata"]["name"]
            for path in rule["http"]["paths"]:
                service = path["backend"]["service"]
                assert service["port"]["name"] in ports[service["name"]]
                routed.add((service["name"], service["port"]["name"]))
    assert {("mapservice-api", "http"), ("mapservice-api", "foxglove")} <= routed
