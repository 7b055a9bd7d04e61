"""Submit a coin_app command to a Ray cluster: the same as ``python -m coin_app submit`` (see coin_app/jobs.py).

Usage: python cluster/submit.py [--address http://HEAD:8265] [--install pip|none] [--wait] -- sweep seeds --smoke
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from coin_app.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(["submit", *sys.argv[1:]]))
