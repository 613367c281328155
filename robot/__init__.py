"""Robot side of mapservice: map tools, the robot agent, the simulator and the interactive robot.

Installed as `mapservice.robot`. Everything that decides (slicing, planning, the simulation
step) is pure and tested without brokers; the modules that talk MQTT/HTTP are thin.
"""

from pathlib import Path

# The map simulated robots drive on when none is given: a checkout's maps/warehouse.yaml
# (a pip install has no maps/; then --map is needed).
DEFAULT_MAP = Path(__file__).resolve().parent.parent / "maps" / "warehouse.yaml"
