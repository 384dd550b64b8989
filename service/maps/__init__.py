"""Maps: validation and versions, the embedded store, put and get, import, build and rendering.

``book`` (what the service accepts as a map and which version it holds), ``store`` (the
file-backed Zenoh storage of ``{prefix}/maps/**``), ``client`` (put a map file, get a stored
map) and ``mapimport`` (ROS grids and laser logs to wire Maps, and map pictures).

May import: ``rlutf``, ``schemas``, ``service.keys``, ``service.infile``. Not the logs, the
cluster, the live service or the command line; following maps on the bus is the live service's
(:mod:`service.live.mapfeed`).
"""
