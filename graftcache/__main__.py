"""`python -m graftcache`: the console script without an installed entry point."""

import sys

from graftcache.cli import main

sys.exit(main())
