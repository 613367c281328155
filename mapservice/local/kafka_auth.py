"""Who may use the embedded Apache Kafka under `mapservice up --auth`: only the service's
components, with a generated password (SASL/PLAIN). Without it any local user who reaches
the loopback port could produce, e.g. command events that robots would then be sent.

SASL/PLAIN rather than SCRAM: the users live in the node's own configuration (its file is
0600, as the secrets are), so a data dir formatted without them keeps working and a new
password takes effect at the next start; SCRAM users are written into the metadata log
when it is formatted, and KRaft's controller listener cannot use SCRAM at all. The
listeners stay on 127.0.0.1 and in clear text, so the password never leaves the machine.
No authorizer: every authenticated user is the service.

tansu has no authentication: under `--auth` on tansu (no Java) anyone local can produce
(README, limits).
"""

from __future__ import annotations

import re

KAFKA_SERVICE_USER = "mapservice"  # every component of the service
KAFKA_NODE_USER = "mapservice-kafka-node"  # the node's own connection to its controller
MECHANISM = "PLAIN"
SECURITY_PROTOCOL = "SASL_PLAINTEXT"
_SAFE = re.compile(r"[A-Za-z0-9_.-]{1,128}")  # inside the JAAS line's quotes
TANSU_NO_AUTH = (
    "tansu has no SASL authentication: Kafka credentials need the embedded Apache Kafka "
    "(a Java runtime; MAPSERVICE_EMBEDDED_KAFKA=apache)"
)


def _jaas(own: tuple[str, str], users: tuple[tuple[str, str], ...]) -> str:
    for name, password in users:
        if not (_SAFE.fullmatch(name) and _SAFE.fullmatch(password)):
            raise ValueError(
                f"Kafka user {name[:40]!r}: names and passwords are 1-128 characters of "
                "A-Z a-z 0-9 _ . - (they are written into the broker's JAAS configuration)"
            )
    accounts = " ".join(f'user_{name}="{password}"' for name, password in users)
    return (
        "org.apache.kafka.common.security.plain.PlainLoginModule required "
        f'username="{own[0]}" password="{own[1]}" {accounts};'
    )


def listener_properties(
    port: int, controller_port: int, sasl_users: tuple[tuple[str, str], ...]
) -> list[str]:
    """A node's listeners: in clear text without users; with users (the first the node's
    own), SASL/PLAIN on the clients' listener and on the controller's, which only the node
    itself may use."""
    if not sasl_users:
        return [
            f"listeners=PLAINTEXT://127.0.0.1:{port},CONTROLLER://127.0.0.1:{controller_port}",
            f"advertised.listeners=PLAINTEXT://127.0.0.1:{port}",
            "controller.listener.names=CONTROLLER",
            "inter.broker.listener.name=PLAINTEXT",
            "listener.security.protocol.map=CONTROLLER:PLAINTEXT,PLAINTEXT:PLAINTEXT",
        ]
    node = sasl_users[0]
    return [
        f"listeners={SECURITY_PROTOCOL}://127.0.0.1:{port},CONTROLLER://127.0.0.1:{controller_port}",
        f"advertised.listeners={SECURITY_PROTOCOL}://127.0.0.1:{port}",
        "controller.listener.names=CONTROLLER",
        f"inter.broker.listener.name={SECURITY_PROTOCOL}",
        f"listener.security.protocol.map=CONTROLLER:{SECURITY_PROTOCOL},"
        f"{SECURITY_PROTOCOL}:{SECURITY_PROTOCOL}",
        f"sasl.enabled.mechanisms={MECHANISM}",
        f"sasl.mechanism.inter.broker.protocol={MECHANISM}",
        f"sasl.mechanism.controller.protocol={MECHANISM}",
        f"listener.name.{SECURITY_PROTOCOL.lower()}.{MECHANISM.lower()}.sasl.jaas.config="
        + _jaas(node, sasl_users),
        f"listener.name.controller.{MECHANISM.lower()}.sasl.jaas.config=" + _jaas(node, (node,)),
    ]


def sasl_client_config(username: str, password: str) -> dict[str, str]:
    """librdkafka's settings for one of the node's users."""
    return {
        "security.protocol": SECURITY_PROTOCOL,
        "sasl.mechanism": MECHANISM,
        "sasl.username": username,
        "sasl.password": password,
    }


def component_env(password: str) -> dict[str, str]:
    """What every component of the service is told (the settings every Kafka client of the
    service, librdkafka's and faust's, is configured from)."""
    return {
        "MAPSERVICE_KAFKA_SECURITY_PROTOCOL": SECURITY_PROTOCOL,
        "MAPSERVICE_KAFKA_SASL_MECHANISM": MECHANISM,
        "MAPSERVICE_KAFKA_USERNAME": KAFKA_SERVICE_USER,
        "MAPSERVICE_KAFKA_PASSWORD": password,
    }
