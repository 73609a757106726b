"""`python -m devtools.tile SOURCE DEST ...` (devtools/tile/cli.py)."""

import sys

from devtools.tile.cli import main

sys.exit(main())
