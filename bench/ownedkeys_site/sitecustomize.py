"""On ``PYTHONPATH`` only in :mod:`bench.ownedkeys`'s service: patches it at start."""

from bench.ownedkeys import install

install()
