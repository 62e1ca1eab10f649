"""``python -m confnav``: the command line."""

import sys

from confnav.cli import main

sys.exit(main())
