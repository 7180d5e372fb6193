"""`python -m flowerpose`: the same command line as the `flowerpose` script."""

import sys

from flowerpose.cli import main

if __name__ == "__main__":  # not when a documentation tool imports every module
    sys.exit(main())
