"""The live service on a Zenoh bus, and the tools that talk to it.

``node`` (:class:`~service.live.node.LocalizationService`: session, subscriptions,
publishing, health and pose queryables), ``dispatch`` (per-robot mailboxes and the worker
shards that run the engine), ``mapfeed`` (maps followed on the bus and fetched on demand),
``stats`` (the health counters), ``sessions`` (zenoh configurations and a free loopback
port), ``queries`` (``rlutf pose|health``), ``demo`` (``rlutf demo``: the service with a
simulated fleet) and ``liveview`` / ``foxview`` / ``foxstatus`` (``--foxglove-port``: the live
view in Foxglove).

May import: ``rlutf``, ``schemas``, ``service.keys``, ``service.config``, ``service.engine``,
``service.maps``, ``service.logs``, ``service.cluster``. Not the command line.
"""
