"""`python -m daemon.cli`: the cdprd command line."""

import sys

from daemon.cli import main

sys.exit(main())
