"""Mosquitto's acl_file, as BrokerFiles writes it, is the MQTT access policy's table on the
real broker: a fleet of every kind of user publishes on every topic the table's rows name
(filled in with the fleet's names, and one level deeper) and each receives through a `#`
subscription; every publish the table allows gets its PUBACK, every other is refused, and
each user receives exactly the topics the table lets it read.

Mosquitto asks its acl_file about each message at delivery, not about the SUBSCRIBE (the
dynamic security plugin refuses the shared ones, test_mosquitto_shared_subscriptions.py), so
one `#` subscription covers every wildcard a user could subscribe to.
"""

from __future__ import annotations

import time
from collections import Counter

from mapservice.adapters.mqtt_auth import GATEWAY_USER, PROCESSORS_USER
from mapservice.adapters.mqtt_policy import Action, access_policy
from tests.fixtures.mosquitto import (
    ProbeClient,
    mosquitto_identities,  # noqa: F401 (a fixture)
)
from tests.fixtures.mqtt_policy_cases import (
    LEGACY_ROBOT,
    ROBOTS,
    allowing_rows,
    concrete_topics,
    fleet,
)


def test_mosquitto_allows_each_row_and_refuses_every_other_combination(
    mosquitto_identities,  # noqa: F811 (the fixture, imported above)
):
    broker = mosquitto_identities
    topics = broker.files.topics
    policy = access_policy(topics)
    # Mosquitto's password file ends a username at its first ':', so a robotId with one
    # cannot log in there (a limit of the file, not of the ACL): the Mosquitto fleet's robots
    # have none.
    users = fleet(legacy=True, robots=tuple(r.replace(":", "") for r in ROBOTS))
    passwords = dict(broker.service_passwords)
    for name in users:
        if name not in (GATEWAY_USER, PROCESSORS_USER):
            passwords[name] = broker.files.add_robot(
                name, legacy_chunks=name == LEGACY_ROBOT
            ).password
    broker.start()
    concrete = concrete_topics(policy, users, topics)
    clients = {name: ProbeClient(broker.port, name, passwords[name]) for name in users}
    try:
        for client in clients.values():
            assert not client.subscribe(["#"])[0].is_failure
        wrong, used, delivered = [], set(), Counter()
        for name, client in clients.items():
            for topic in concrete:
                rows = allowing_rows(policy, users[name], name, Action.PUBLISH, topic)
                code = client.publish(topic)
                assert code is not None, f"no PUBACK for {name} on {topic}"
                if code.is_failure == bool(rows):
                    wrong.append(
                        (name, "publish", topic, "refused" if code.is_failure else "allowed")
                    )
                used.update(rows)
                if not code.is_failure:
                    delivered[topic] += 1
        expected = {
            name: Counter(
                {
                    t: n
                    for t, n in delivered.items()
                    if allowing_rows(policy, kinds, name, Action.SUBSCRIBE, t)
                }
            )
            for name, kinds in users.items()
        }
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and any(
            len(clients[n].received) < sum(expected[n].values()) for n in users
        ):
            time.sleep(0.05)
        time.sleep(0.3)  # nothing beyond either
        for name, kinds in users.items():
            got = Counter(clients[name].received)
            for topic in set(got) | set(expected[name]):
                if got[topic] != expected[name][topic]:
                    wrong.append((name, "read", topic, f"{got[topic]} of {expected[name][topic]}"))
            for topic in got:
                used.update(allowing_rows(policy, kinds, name, Action.SUBSCRIBE, topic))
    finally:
        for client in clients.values():
            client.close()
    assert wrong == [], f"{len(wrong)} answers differ from the table, e.g. {wrong[:10]}"
    assert used == set(policy), f"rows no case exercised: {set(policy) - used}"
    published = len(users) * len(concrete)  # 8 users x 54 topics with the default topics
    assert 0 < sum(delivered.values()) < published / 10, (published, sum(delivered.values()))
