"""Robot side of mapservice: map tools, the robot agent, the simulator and the interactive robot.

Installed as `mapservice.robot`. Everything that decides (slicing, planning, the simulation
step) is pure and tested without brokers; the modules that talk MQTT/HTTP are thin.
"""
