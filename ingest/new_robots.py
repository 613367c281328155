"""How many robot ids the gateway admits that it has not seen before.

Where the broker does not authenticate robots (open mode), anyone may publish a pose under
any robotId: 100,000 made-up ids made every `/api/v1/robots` call 31 MB for the whole
retention. The gateway therefore admits at most MAPSERVICE_INGEST_NEW_ROBOTS_LIMIT new ids
(e.g. 10000/minute, the `limits` notation); a message of one more new robot becomes a dead
letter `too_many_new_robots`, while robots already seen pass as always. A fleet that
starts up at once stays within it; the ids seen are remembered up to REMEMBER (the oldest
forgotten first: such a robot counts as new once more when it comes back).
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from limits import RateLimitItem, parse_many
from limits.storage import MemoryStorage
from limits.strategies import MovingWindowRateLimiter

REMEMBER = 100_000
_KEY = "new-robot-ids"


class NewRobots:
    def __init__(self, limit: str, remember: int = REMEMBER) -> None:
        self.items: list[RateLimitItem] = parse_many(limit) if limit.strip() else []
        self.limiter = MovingWindowRateLimiter(MemoryStorage())
        self.remember = remember
        self._known: OrderedDict[str, None] = OrderedDict()
        self._lock = threading.Lock()

    def refusal(self, robot_id: str) -> str | None:
        """None when `robot_id` may pass (seen before, or a new one within the limit);
        else the dead letter's detail."""
        if not self.items:
            return None
        with self._lock:
            if robot_id in self._known:
                self._known.move_to_end(robot_id)
                return None
            over = next((item for item in self.items if not self.limiter.test(item, _KEY)), None)
            if over is not None:
                return (
                    f"robot {robot_id[:64]!r} is new to this gateway and more than {over} "
                    "new robot ids arrived (MAPSERVICE_INGEST_NEW_ROBOTS_LIMIT); robots "
                    "already seen are unaffected. A real fleet growing faster: raise the "
                    "limit; otherwise give robots broker credentials (`mapservice robot add`)"
                )
            for item in self.items:
                self.limiter.hit(item, _KEY)
            self._known[robot_id] = None
            if len(self._known) > self.remember:
                self._known.popitem(last=False)
            return None
