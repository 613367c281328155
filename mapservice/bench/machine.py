"""The machine a benchmark ran on: CPU, memory, the brokers' and packages' versions, the
checkout's commit. Every benchmark's JSON records these beside its figures.
"""

from __future__ import annotations

import os
import platform
import shutil
import subprocess
from pathlib import Path
from typing import Any

import psutil


def _first_line(cmd: list[str]) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unknown ({exc})"
    text = (out.stdout or out.stderr).strip().splitlines()
    return text[0] if text else "unknown"


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo ("unknown" elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def embedded_kafka_fact() -> str:
    """Which Kafka the runs' stacks embed (MAPSERVICE_EMBEDDED_KAFKA)."""
    from mapservice.local import kafka_broker
    from mapservice.settings import Settings

    if kafka_broker.embedded_choice(Settings().embedded_kafka) == "apache":
        return f"Apache Kafka {kafka_broker.kafka_version()} (one KRaft node)"
    return "tansu (memory)"


def machine_facts() -> dict[str, Any]:
    model = cpu_model()
    try:
        from mapservice.local.embedded import tansu_binary

        tansu = _first_line([str(tansu_binary()), "--version"])
    except Exception as exc:  # noqa: BLE001 - a fact we could not read, not a failure
        tansu = f"unknown ({exc})"
    mosquitto_bin = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    mosquitto = (
        _first_line([mosquitto_bin, "-h"]) if os.path.exists(mosquitto_bin) else "not installed"
    )
    versions = {}
    for dist in (
        "chdb",
        "clickhouse-connect",
        "faust-streaming",
        "aiokafka",
        "confluent-kafka",
        "paho-mqtt",
        "fastapi",
        "uvicorn",
    ):
        try:
            from importlib.metadata import version

            versions[dist] = version(dist)
        except Exception:  # noqa: BLE001
            versions[dist] = "unknown"
    return {
        "nproc": len(os.sched_getaffinity(0))
        if hasattr(os, "sched_getaffinity")
        else os.cpu_count(),
        "cpu_model": model,
        "ram_bytes": psutil.virtual_memory().total,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "tansu": tansu,
        "kafka": embedded_kafka_fact(),
        "mosquitto": mosquitto,
        "packages": versions,
        "loadavg_at_start": os.getloadavg(),
        "git": _git_state(),
    }


def _git_state() -> dict[str, Any]:
    from mapservice.local.checkout import ROOT as root

    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain"],
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        ).stdout.splitlines()
    except (OSError, subprocess.TimeoutExpired):
        return {}
    return {"head": head, "uncommitted": [line.strip() for line in dirty]}
