"""The agents' side of the distributed backend: wire protocol, transport, the agent and its
process, launching. The world that runs the closed loop is :mod:`torch_gpmpc.sim.distributed`."""
