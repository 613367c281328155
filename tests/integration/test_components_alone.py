"""Each component runs alone, configured only from the environment, as in production."""

from __future__ import annotations

import re
import signal
import time

import httpx

from mapservice.local.embedded import free_port, wait_for_port
from mapservice.local.stack import Stack

from .test_pipeline import now_ms, pose_and_chunk_messages, publish_all


def test_gateway_processors_and_api_run_as_separate_processes(tmp_path):
    """`mapservice gateway` and `mapservice processors` ingest alone; later `mapservice api` serves it."""
    stack = Stack(tmp_path / "alone", mqtt="mosquitto")
    procs = []
    try:
        stack.start_brokers()
        gw_port, pr_port = free_port(), free_port()
        processors = stack.spawn("processors", "processors", "--health-port", str(pr_port))
        procs.append(processors)
        wait_for_port(pr_port, timeout_s=120, proc=processors, what="processors")
        stack.wait_healthy(f"http://127.0.0.1:{pr_port}/healthz", "processors", processors)
        gateway = stack.spawn("gateway", "gateway", "--health-port", str(gw_port))
        procs.append(gateway)
        wait_for_port(gw_port, proc=gateway, what="gateway")
        stack.wait_healthy(f"http://127.0.0.1:{gw_port}/healthz", "gateway", gateway)

        start = now_ms() - 30_000
        poses, chunks = pose_and_chunk_messages("alone", robots=4, per_robot=10, start_ms=start)
        publish_all(stack, poses + chunks)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            text = httpx.get(f"http://127.0.0.1:{pr_port}/metrics").text
            stored = sum(
                float(v)
                for v in re.findall(
                    r'^mapservice_sink_events_total\{topic="mapservice\.(?:pose|chunk)-events\.v1"\} (\S+)$',
                    text,
                    re.M,
                )
            )
            if stored >= len(poses) + len(chunks):
                break
            time.sleep(0.3)
        assert stored >= len(poses) + len(chunks)
        for proc in procs:
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(30) == 0
        procs.clear()

        # chDB allows one opener per directory: the API starts once the processors are gone.
        api = stack.spawn("api", "api")
        procs.append(api)
        wait_for_port(stack.api_port, timeout_s=60, proc=api, what="api")
        rows = httpx.get(
            f"{stack.api_url}/api/v1/poses", params={"from": start, "to": start + 60_000}
        ).json()
        assert len([r for r in rows if r["robotId"].startswith("alone")]) == len(poses)
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()
        stack.stop()
