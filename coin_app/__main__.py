"""``python -m coin_app``: the command line."""

import sys

from coin_app.cli import main

sys.exit(main())
