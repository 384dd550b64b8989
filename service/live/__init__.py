"""The live service on a Zenoh bus, and the tools that talk to it.

``node`` (:class:`~service.live.node.LocalizationService`: session, subscriptions,
publishing, health and pose queryables), ``dispatch`` (per-robot mailboxes and the worker
shards that run the engine), ``mapfeed`` (maps followed on the bus and fetched on demand),
``stats`` (the health counters), ``sessions`` (zenoh configurations and a free loopback
port), ``queries`` (``rlutf pose|health``) and ``liveview`` / ``foxview`` / ``foxstatus``
(``--foxglove-port``: the live view in Foxglove). The simulated fleet and ``rlutf demo`` live in
:mod:`service.sim`, a client of this part.

May import: ``rlutf``, ``schemas``, ``service.keys``, ``service.config``, ``service.engine``,
``service.maps``, ``service.logs``, ``service.cluster``. Not the command line.
"""
