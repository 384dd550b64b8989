"""Everything with I/O around the pure ``rlutf`` library, in sub-packages by concern.

======================= ===================================================================
``service.keys``,       the WIRE.md key layout and input models; the effective configuration
``service.config``
``service.prepared``    :class:`~service.prepared.PreparedMap`, a map version built and
                        indexed by the first update that needs it
``service.engine``      :class:`~service.engine.FleetEngine`, the per-fleet state machine that
                        the live service and replay both run
``service.maps``        map validation and versions, the file-backed store, map put and get,
                        import and build from grids and logs, rendering
``service.cluster``     membership, ownership of robots, handover between instances
``service.logs``        MCAP layout, reading, recording, Foxglove views, replay, audit, plots
``service.live``        the service on a Zenoh bus: session, subscriptions, dispatch to
                        workers, publishing, health, map following, client queries, the demo
``service.cli``         the ``rlutf`` command line
======================= ===================================================================

Imports never go up this table, and no two parts import each other; each sub-package's
docstring says what it may import (``tests/service/test_layout.py`` checks both).
"""
