"""A watchdog that removes a local sweep's Ray processes once its driver is gone, even after ``kill -9``.

``ray.init`` starts the local Ray's processes (GCS, raylet, dashboard and runtime-env agents,
workers) as children that inherit the driver's environment. A driver stopped normally, by Ctrl-C
or by SIGTERM shuts them down; a driver killed with SIGKILL cannot, and Ray's
``DashboardAgent`` and ``RuntimeEnvAgent`` were left behind. :func:`start_reaper` marks the
environment with a fresh id (``COIN_SWEEP_RUN``) before the local Ray starts and spawns a small
process in its own session that waits for the driver's pid to disappear, then kills every
process whose environment carries that id, and no other. Linux only (it reads ``/proc``);
elsewhere it does nothing.
"""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

MARKER = "COIN_SWEEP_RUN"

# The watchdog's program: wait for the driver pid, then SIGKILL every process carrying MARKER=<id>.
_WATCHDOG = """
import os, signal, sys, time
from pathlib import Path
driver, tag = int(sys.argv[1]), sys.argv[2].encode()  # MARKER=<id>
def alive(pid):
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False
while alive(driver):
    time.sleep(1.0)
for _ in range(3):
    for env in Path("/proc").glob("[0-9]*/environ"):
        try:
            if tag in env.read_bytes().split(b"\\0"):
                os.kill(int(env.parent.name), signal.SIGKILL)
        except (OSError, ValueError):
            pass
    time.sleep(1.0)
"""


def start_reaper() -> str | None:
    """Mark this process's environment for the Ray it is about to start and spawn the watchdog; returns the id (None off Linux)."""
    if not Path("/proc/self/environ").is_file():
        return None
    run_id = uuid.uuid4().hex
    env = {k: v for k, v in os.environ.items() if k != MARKER}  # the watchdog itself carries no mark
    subprocess.Popen(
        [sys.executable, "-c", _WATCHDOG, str(os.getpid()), f"{MARKER}={run_id}"],
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    os.environ[MARKER] = run_id
    return run_id


def clear_mark() -> None:
    """Stop marking processes this driver starts from now on (those already marked stay marked)."""
    os.environ.pop(MARKER, None)
