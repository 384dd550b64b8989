"""Logs: the MCAP layout of WIRE.md, reading and writing it, recording, replay and audit.

``mcapfile`` (layout and writer), ``mcapread`` (reader with clear errors, over ``mcaprecords``,
``mcapchunks`` and ``mcaporder``: records, chunks and order, each within a bound),
``recording`` (the recorder protocol the live service holds) and ``mcaplog`` (the MCAP
recorder), ``foxglove`` (views of the logged messages), ``runs`` (which files belong to one
run: ``rlutf.run``), ``partfile`` (unfinished ``.mcap.part`` logs), ``manifest`` (the records
``rlutf.manifest`` and ``rlutf.recovered``), ``completeness`` (what of a run was not read),
``replay`` and ``replayconfig`` (the engine over one run's inputs), ``audit`` and ``plots``
(recorded against recomputed poses), ``logtools`` (``rlutf log info``), ``salvage`` (``rlutf log
recover``), ``mcapmaps`` (scans with known poses, for ``rlutf map build``).

May import: ``rlutf``, ``schemas``, ``service.keys``, ``service.config``, ``service.engine``,
``service.maps``, ``service.infile``. Not the cluster, the live service or the command line:
replay runs the engine with no Zenoh.
"""
