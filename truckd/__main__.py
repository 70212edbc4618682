"""``python -m truckd``: the same command line as the ``truckd`` script."""

import sys

from truckd.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
