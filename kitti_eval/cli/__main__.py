"""``python -m kitti_eval.cli``: the command line, as the console script runs it but with a normal exit."""

import sys

from . import main

if __name__ == "__main__":  # not when a walk over the package imports this module
    sys.exit(main())
