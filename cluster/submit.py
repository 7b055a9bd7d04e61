"""Submit a coin_app command to a Ray cluster: runs ``python -m coin_app submit`` (the job client is cluster/jobs.py).

Usage: python cluster/submit.py [--address http://HEAD:8265] [--install pip|none] [--wait] -- sweep seeds --smoke
"""

import os
import sys
from pathlib import Path

if __name__ == "__main__":
    os.chdir(Path(__file__).resolve().parent.parent)  # the repository root, where ``coin_app`` is importable
    os.execv(sys.executable, [sys.executable, "-m", "coin_app", "submit", *sys.argv[1:]])
