"""The names the plant keys accept (``plant``, ``plant_vehicle``, ``plant_wind``); the plants
themselves live in :mod:`torch_gpmpc.dynamics.plants` and :mod:`torch_gpmpc.dynamics.rotorpy_plant`."""

PLANTS = ("model", "rotorpy")
VEHICLES = ("crazyflie", "hummingbird")
WINDS = ("none", "constant", "sine", "dryden")
