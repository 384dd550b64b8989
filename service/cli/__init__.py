"""The command line: the ``rlutf`` entry (:mod:`service.cli.main`) and one module per group.

Each group module (``serve``, ``maps``, ``query``, ``logs``) has a ``register(sub)`` that adds
its commands to the ``rlutf`` subparsers, and command functions that map the other
sub-packages' errors to exit codes; shared flag groups and exit codes are in
:mod:`service.cli.flags`. Only this package prints usage and exits.

May import: every other part of ``service`` (heavy ones lazily, inside the commands, so that
``rlutf --help`` starts fast). Nothing imports it.
"""
