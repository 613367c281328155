"""The load fleet's tests publish through a real Mosquitto."""

from tests.fixtures.mosquitto import mosquitto  # noqa: F401 (a fixture)
