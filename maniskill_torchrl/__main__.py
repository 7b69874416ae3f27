"""``python -m maniskill_torchrl``: the ``maniskill-torchrl`` command line."""

import sys

from maniskill_torchrl.cli import main

if __name__ == "__main__":
    sys.exit(main())
