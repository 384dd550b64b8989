"""The cluster: which live instance localizes which robot, and the handover between them.

``membership`` (liveliness tokens, rendezvous hashing of robots over instances, fetching the
last published poses), ``ownership`` (the robots one instance owns, the odometry tail it
keeps of the others, and seeding a robot it takes over) and ``names`` (one live instance per
name, also when two of one name start together).

May import: ``rlutf``, ``schemas``, ``service.keys``, eclipse-zenoh. Not the maps, the logs,
the live service or the command line; the live service wires the cluster in.
"""
