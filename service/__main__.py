"""``python -m service``: the ``rlutf`` command line, for environments without the script."""

import sys

from service.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
