"""``python -m neuromotor``: the command line (:mod:`neuromotor.cli`)."""

import sys

from neuromotor.cli import main

if __name__ == "__main__":
    sys.exit(main())
