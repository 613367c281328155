"""What goes wrong on the simulated floor, on purpose and at a real floor's rates, so that the
demo has incidents to show: now and then a robot stands still on its route for a while (an
obstacle, a person in the way), drops off the network, or drives on below its charge level
before it goes to a charger. `robot/sim.py` steps them; the durations and levels come from
the incident rules' thresholds (`for_incidents`), crossing them by a margin, so every one
of them is an incident the rules find, and nothing near a threshold flickers.

Each is a robot's own Poisson process in simulated time, seeded by the simulation's seed:
a generator is made only when one starts or ends (rarely), never per robot per tick.
"""

from __future__ import annotations

import random
from dataclasses import replace

from mapservice.core.incident_model import IncidentThresholds

from .sim_model import Robot, SimConfig, evolve

# A robot's mean time between its own stalls and between its silences: five robots make
# about three of each an hour.
EVERY_S = 5400.0
# Of the charges, those a robot starts late (below the battery_low line): with a charge
# every quarter hour or so, about three an hour for five robots.
LATE_CHARGE_SHARE = 0.15
# How far past its threshold each behaviour goes: a stall lasts 1.4-4 times the stuck
# window, a silence 1.5-6 times the offline threshold, a late charge starts at 75-95 % of
# the battery_low level.
STALL_TIMES = (1.4, 4.0)
SILENCE_TIMES = (1.5, 6.0)
LATE_LEVEL_SHARE = (0.75, 0.95)
GIVE_WAY_TIMES = 1.5
STATION_SPACING_TIMES = 4.0
GIVE_WAY_STUCK_SHARE = 0.6  # of the stuck window, the longest a robot stands giving way
DRIVING = ("to_pick", "to_drop", "to_charger", "leave_zone")


def for_incidents(config: SimConfig, th: IncidentThresholds) -> SimConfig:
    """`config` with the floor's incidents on, sized against the rules' thresholds `th`."""
    stuck_s, offline_s = th.stuck_ms / 1000, th.offline_after_ms / 1000
    low = th.battery_low_percent
    return replace(
        config,
        stall_every_s=EVERY_S,
        stall_s=(stuck_s * STALL_TIMES[0], stuck_s * STALL_TIMES[1]),
        dropout_every_s=EVERY_S,
        dropout_s=(offline_s * SILENCE_TIMES[0], offline_s * SILENCE_TIMES[1]),
        late_charge_share=LATE_CHARGE_SHARE,
        late_charge_battery=(low * LATE_LEVEL_SHARE[0], low * LATE_LEVEL_SHARE[1]),
        # robots give way to each other, keeping well clear of a near miss: one happens
        # where waiting ran out
        give_way_m=th.near_miss_m * GIVE_WAY_TIMES,
        give_way_s=stuck_s * GIVE_WAY_STUCK_SHARE,
        station_spacing_m=th.near_miss_m * STATION_SPACING_TIMES,
        # the ordinary charge starts well above the line
        low_battery=max(config.low_battery, low * 1.5),
    )


def _due_in_ms(rng: random.Random, every_s: float) -> int:
    return int(rng.expovariate(1.0 / every_s) * 1000) + 1000


def first_due(config: SimConfig, robot: Robot, rng: random.Random, t_ms: int) -> Robot:
    """The robot with its first stall and silence scheduled (if the config has them)."""
    if config.stall_every_s > 0:
        robot = evolve(robot, next_stall_ms=t_ms + _due_in_ms(rng, config.stall_every_s))
    if config.dropout_every_s > 0:
        robot = evolve(robot, next_dropout_ms=t_ms + _due_in_ms(rng, config.dropout_every_s))
    return robot


def _rng(seed: int, tick: int, robot: Robot, what: str) -> random.Random:
    return random.Random(f"{seed}:{tick}:{robot.robot_id}:{what}")


def stalled(config: SimConfig, robot: Robot, t_ms: int, seed: int, tick: int) -> Robot | None:
    """The robot after a tick of standing on its route, if it stands this tick (a stall
    starts only while it drives); None if it drives on."""
    if config.stall_every_s <= 0:
        return None
    if robot.stall_s <= 0:
        if t_ms < robot.next_stall_ms or robot.task not in DRIVING or not robot.waypoints:
            return None
        rng = _rng(seed, tick, robot, "stall")
        robot = evolve(robot, stall_s=rng.uniform(*config.stall_s))
    left = robot.stall_s - config.dt_s
    battery = max(0.0, robot.battery - config.idle_drain_per_s * config.dt_s)
    if left > 0:
        return evolve(robot, stall_s=left, battery=battery)
    rng = _rng(seed, tick, robot, "stall-over")
    due = t_ms + _due_in_ms(rng, config.stall_every_s)
    return evolve(robot, stall_s=0.0, battery=battery, next_stall_ms=due)


def network(config: SimConfig, robot: Robot, t_ms: int, seed: int, tick: int) -> Robot:
    """The robot's connection after this tick: a silence starts when due, and runs out."""
    if config.dropout_every_s <= 0:
        return robot
    if robot.silent_s > 0:
        left = robot.silent_s - config.dt_s
        if left > 0:
            return evolve(robot, silent_s=left)
        rng = _rng(seed, tick, robot, "online")
        return evolve(
            robot, silent_s=0.0, next_dropout_ms=t_ms + _due_in_ms(rng, config.dropout_every_s)
        )
    if t_ms >= robot.next_dropout_ms:
        rng = _rng(seed, tick, robot, "offline")
        return evolve(robot, silent_s=rng.uniform(*config.dropout_s))
    return robot


def charge_below(config: SimConfig, robot: Robot) -> float:
    """The level below which the robot goes to a charger."""
    return robot.charge_below if robot.charge_below >= 0 else config.low_battery


def next_charge_level(config: SimConfig, rng: random.Random) -> float:
    """The level the robot, charged, will next go to a charger at: now and then a late one."""
    if config.late_charge_share > 0 and rng.random() < config.late_charge_share:
        return round(rng.uniform(*config.late_charge_battery), 1)
    return -1.0
