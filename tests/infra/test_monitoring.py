"""The Grafana dashboard and the Prometheus alerts name only metrics the code exports."""

from __future__ import annotations

import json
import re

import pytest
import yaml
from fastapi.testclient import TestClient
from prometheus_client import REGISTRY

from tests.fixtures.paths import ROOT

MONITORING = ROOT / "infra" / "k8s" / "monitoring"
# Metrics from outside mapservice that the rules use on purpose.
EXTERNAL = {"up", "kube_pod_status_ready"}
PROMQL_WORDS = {
    "and",
    "or",
    "unless",
    "by",
    "without",
    "on",
    "ignoring",
    "group_left",
    "group_right",
    "bool",
    "offset",
    "le",
    "inf",
    "nan",
}
SUFFIXES = {
    "counter": ("_total", "_created"),
    "histogram": ("_bucket", "_sum", "_count", "_created"),
    "gauge": ("",),
    "summary": ("_sum", "_count", "_created", ""),
    "info": ("_info",),
}


def exported_metric_names() -> set[str]:
    """Every sample name the gateway, processors and API processes register (series or not)."""
    import mapservice.adapters.kafka_batch_source  # noqa: F401
    import mapservice.ingest.metrics  # noqa: F401
    import mapservice.processors.advertiser  # noqa: F401
    import mapservice.processors.app  # noqa: F401
    import mapservice.processors.history_consumer  # noqa: F401
    import mapservice.processors.views  # noqa: F401
    from mapservice.api.app import create_app
    from mapservice.settings import Settings
    from mapservice.testing.memory_store import MemoryStore

    # The API's request metrics are created with its middleware, on the first request.
    TestClient(create_app(Settings(), MemoryStore())).get("/api/v1/stats")
    names = set()
    for family in REGISTRY.collect():
        for suffix in SUFFIXES.get(family.type, ("",)):
            names.add(family.name + suffix)
    return names


def metric_names(expr: str) -> set[str]:
    """The metric names in a PromQL expression: identifiers that are not functions,
    keywords, label names or durations."""
    expr = re.sub(r"\{[^}]*\}", "", expr)  # label matchers
    expr = re.sub(r"\[[^\]]*\]", "", expr)  # range selectors
    expr = re.sub(r"\b(by|without|on|ignoring|group_left|group_right)\s*\([^)]*\)", "", expr)
    expr = re.sub(r'"[^"]*"', "", expr)  # string arguments
    expr = re.sub(r"(?<![a-zA-Z0-9_:])\d+(\.\d+)?([eE][-+]?\d+)?", "", expr)  # numbers
    names = set()
    for m in re.finditer(r"[a-zA-Z_:][a-zA-Z0-9_:]*", expr):
        word, rest = m.group(0), expr[m.end() :].lstrip()
        if (
            rest.startswith("(")
            or word.lower() in PROMQL_WORDS
            or re.fullmatch(r"\d+[smhdwy]", word)
        ):
            continue
        names.add(word)
    return names


def dashboard_exprs() -> list[str]:
    dashboard = json.loads((MONITORING / "grafana-dashboard.json").read_text())
    return [t["expr"] for p in dashboard["panels"] for t in p.get("targets", [])]


def rule_exprs() -> list[str]:
    (rules,) = [
        d
        for d in yaml.safe_load_all((MONITORING / "prometheus-rules.yaml").read_text())
        if d and d["kind"] == "PrometheusRule"
    ]
    return [r["expr"] for g in rules["spec"]["groups"] for r in g["rules"]]


def test_metric_name_extraction_finds_names_and_skips_the_rest() -> None:
    """The PromQL reader returns metric names only (so the checks below can fail)."""
    expr = (
        'histogram_quantile(0.99, sum by (le, path) (rate(x_bucket{a="b"}[5m]))) '
        "/ clamp_min(sum(rate(y_total[5m])), 1e-9) > 0 and on (pod) up == 0"
    )
    assert metric_names(expr) == {"x_bucket", "y_total", "up"}


@pytest.mark.parametrize("source", ["dashboard", "rules"])
def test_queries_name_only_exported_metrics(source: str) -> None:
    """Every metric a dashboard panel or an alert names is registered by a component (or is a known external one)."""
    exprs = dashboard_exprs() if source == "dashboard" else rule_exprs()
    assert exprs
    used = set().union(*(metric_names(e) for e in exprs))
    unknown = used - exported_metric_names() - EXTERNAL
    assert not unknown, f"not exported by any component: {sorted(unknown)}"


def test_the_alerts_cover_what_operators_need() -> None:
    """Alerts exist for lag, dead-letter rate, insert failures, a history not stored now,
    stuck in-flight messages and readiness."""
    (rules,) = [
        d
        for d in yaml.safe_load_all((MONITORING / "prometheus-rules.yaml").read_text())
        if d and d["kind"] == "PrometheusRule"
    ]
    alerts = {r["alert"]: r["expr"] for g in rules["spec"]["groups"] for r in g["rules"]}
    needed = {
        "mapservice_consumer_lag_records",
        "mapservice_gateway_rejected_total",
        "mapservice_sink_insert_failures_total",
        "mapservice_history_insert_failing",
        "mapservice_gateway_in_flight",
        "kube_pod_status_ready",
    }
    assert needed <= set().union(*(metric_names(e) for e in alerts.values()))
    for rule in (r for g in rules["spec"]["groups"] for r in g["rules"]):
        assert rule["annotations"]["summary"] and rule["labels"]["severity"] in (
            "warning",
            "critical",
        )


def test_the_dashboard_is_grafana_json_with_a_panel_per_component() -> None:
    """The dashboard has gateway, processors and API rows and a datasource variable."""
    dashboard = json.loads((MONITORING / "grafana-dashboard.json").read_text())
    rows = [p["title"] for p in dashboard["panels"] if p["type"] == "row"]
    assert [r.split(" ")[0] for r in rows] == ["Gateway", "Processors", "API"]
    assert {v["name"] for v in dashboard["templating"]["list"]} >= {"datasource", "namespace"}
