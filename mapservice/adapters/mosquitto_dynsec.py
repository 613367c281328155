"""The subscriptions Mosquitto's acl_file cannot refuse: shared ones.

Mosquitto 2.0's acl_file is not asked about a SUBSCRIBE at all (only each message, at
delivery). A robot could then subscribe to `$share/<the gateways' group>/iot/coordinates/#`:
the broker counts it as one more member of the gateways' group, hands it its turn of every
message, denies it each one at delivery and drops it, so the gateways lose that share of the
fleet's messages although every robot got its PUBACK. Mosquitto's dynamic security plugin
checks every SUBSCRIBE with the filter as sent (`$share/...` included), so it refuses these.

It is used here for that one rule: every robot, VDA 5050 vehicle and master control is a
client in the plugin's file, without a password (so the password file still authenticates
it) and with a role that denies any `$share/#` subscription. Everything else the plugin
leaves to the acl_file: its default access is "no opinion", which makes Mosquitto ask the
next check. The service's own users are not in it (the gateways subscribe through `$share`).
Publishing to a `$share/...` topic is refused by Mosquitto itself for everyone.
"""

from __future__ import annotations

import json
from collections.abc import Iterable

NO_SHARED_SUBSCRIPTIONS_ROLE = "no-shared-subscriptions"
SHARED_SUBSCRIPTIONS = "$share/#"


def render_dynsec(usernames: Iterable[str]) -> str:
    """The dynamic security plugin's configuration file (JSON) for these users."""
    config = {
        # false: the plugin defers to the acl_file wherever its own rules do not match.
        "defaultACLAccess": {
            "publishClientSend": False,
            "publishClientReceive": False,
            "subscribe": False,
            "unsubscribe": False,
        },
        "clients": [
            {"username": name, "roles": [{"rolename": NO_SHARED_SUBSCRIPTIONS_ROLE}]}
            for name in sorted(set(usernames))
        ],
        "groups": [],
        "roles": [
            {
                "rolename": NO_SHARED_SUBSCRIPTIONS_ROLE,
                "acls": [
                    {
                        "acltype": "subscribePattern",
                        "topic": SHARED_SUBSCRIPTIONS,
                        "allow": False,
                        "priority": 0,
                    }
                ],
            }
        ],
    }
    return json.dumps(config, indent=1) + "\n"
