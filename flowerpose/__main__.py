"""`python -m flowerpose`: the same command line as the `flowerpose` script."""

import sys

from flowerpose.cli import main

sys.exit(main())
