"""Ray job submission: ``python -m coin_app submit|job`` (a wrapper of ``ray job submit|status|logs|stop``).

``submit`` sends ``python -m coin_app <command ...>`` to a cluster's job server with a runtime
environment built from this repository:

* ``working_dir``: the repository root (its code, ``tuning/`` and ``cluster/``), minus
  ``EXCLUDES`` (virtualenvs, runs, git data, docs images), uploaded by Ray;
* ``pip``: the exact pins of ``requirements.txt`` (``install="pip"``, the default), so every
  node runs the versions this repository was tested with; ``install="none"`` when the
  cluster's image already has them (``cluster/Dockerfile``);
* ``env_vars``: ``OMP_NUM_THREADS=1`` (trials share nodes; one thread per process).

Clusters with Ray's token authentication (on by default in Ray 2.60 where a token exists)
need the cluster's token in ``RAY_AUTH_TOKEN`` or ``~/.ray/auth_token`` on the submitting
machine; it is sent as ``ray start`` would.

Inside the job Ray sets ``RAY_ADDRESS``, so the sweep joins the cluster. The job id comes
back at once; ``job status|logs|stop ID`` follow it; ``--wait`` follows the logs to the end.
"""

from __future__ import annotations

import re
import shlex
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from ray.job_submission import JobSubmissionClient

from coin_app.evaluation.limits import check_timeout

REPO = Path(__file__).resolve().parent.parent
DEFAULT_ADDRESS = "http://127.0.0.1:8265"
EXCLUDES = [".git", ".venv", "venv", "runs", "**/__pycache__", "*.png", "*.gif", ".ruff_cache", ".pytest_cache"]
INSTALL_MODES = ("pip", "none")
TERMINAL = ("SUCCEEDED", "FAILED", "STOPPED")
AGENT_WAIT_S = 120.0  # how long submit retries while a fresh head's job agent starts


def pinned_requirements(repo: Path = REPO) -> list[str]:
    """The ``name==version`` lines of the repository's ``requirements.txt``."""
    path = repo / "requirements.txt"
    if not path.is_file():
        raise ValueError(f"{path} not found: submit runs from a coin_app checkout")
    lines = [ln.split("#")[0].strip() for ln in path.read_text().splitlines()]
    return [ln for ln in lines if "==" in ln]


def runtime_env(install: str = "pip", repo: Path = REPO) -> dict[str, Any]:
    """The job's runtime environment (see module doc)."""
    if install not in INSTALL_MODES:
        raise ValueError(f"bad install mode {install!r}; allowed: {', '.join(INSTALL_MODES)}")
    env: dict[str, Any] = {"working_dir": str(repo), "excludes": list(EXCLUDES), "env_vars": {"OMP_NUM_THREADS": "1"}}
    if install == "pip":
        env["pip"] = {"packages": pinned_requirements(repo), "pip_check": False}
    return env


def client(address: str | None) -> Any:
    """A job-submission client of the cluster at ``address`` (its dashboard URL); a clear error if unreachable."""
    address = address or DEFAULT_ADDRESS
    _use_local_token()
    parsed = urlparse(address)
    if parsed.scheme not in ("http", "https") or not parsed.hostname:
        raise ValueError(f"bad --address {address!r}; allowed: the job server URL http(s)://HOST:PORT (dashboard, default port 8265)")
    try:
        return JobSubmissionClient(address)
    except (ConnectionError, RuntimeError, ValueError, OSError) as exc:
        raise ValueError(f"cannot reach a Ray job server at {address}: {exc}") from exc


def _use_local_token() -> None:
    """Send the Ray auth token (``RAY_AUTH_TOKEN`` or ``~/.ray/auth_token``) if there is one, as ``ray start`` does.

    Ray 2.60 turns token authentication on for clusters started where a token exists; its job
    client only sends the token when token mode is on in the client process.
    """
    try:  # optional: private Ray API, the only one that also refreshes the auth mode Ray cached at import (RAY_AUTH_MODE is read once)
        from ray._private.authentication.authentication_token_setup import maybe_enable_token_auth_if_token_available
    except ImportError:  # a Ray without token authentication
        return
    maybe_enable_token_auth_if_token_available(warn_if_disabled=False)


def submit(
    command: list[str],
    address: str | None = None,
    install: str = "pip",
    submission_id: str | None = None,
    check_command: Callable[[list[str]], None] | None = None,
) -> str:
    """Submit ``python -m coin_app <command>`` as a Ray job; returns the job id.

    ``check_command`` (the CLI passes its parser) refuses a bad command here, not on the cluster.
    """
    if not command:
        raise ValueError("nothing to submit; give a coin_app command after --, e.g. -- sweep seeds --smoke")
    if command[0] in ("submit", "job"):
        raise ValueError(f"cannot submit {command[0]!r} as a job; allowed: a training, sweep or evaluation command")
    if check_command is not None:
        check_command(command)
    if command[0] == "sweep" and not any(c.startswith("--storage") for c in command):
        print("warning: without --storage the sweep's results stay in the job's temporary working dir on the head node")
    env = runtime_env(install)
    entrypoint = "python -m coin_app " + shlex.join(command)
    c = client(address)
    deadline = time.perf_counter() + AGENT_WAIT_S
    while True:  # a head that just started answers "No available agent" until its dashboard agent is up
        try:
            return c.submit_job(entrypoint=entrypoint, runtime_env=env, submission_id=submission_id)
        except RuntimeError as exc:
            if "No available agent" not in str(exc) or time.perf_counter() > deadline:
                raise ValueError(f"the job server at {address or DEFAULT_ADDRESS} refused the job: {server_reason(exc)}") from exc
            time.sleep(2.0)


def server_reason(exc: BaseException) -> str:
    """The job server's reason in one line. Its answer may carry its own (nested) tracebacks: then their first line's
    prefix and the last exception line (``ValueError: Job with submission_id X already exists. ...``), else its first line."""
    lines = [line.strip() for line in str(exc).strip().splitlines() if line.strip().strip(".")]
    if not lines:
        return type(exc).__name__
    if "Traceback" in lines[0]:
        raised = [line for line in lines[1:] if re.match(r"^[\w.]+(Error|Exception): ", line)]
        if raised:
            return f"{lines[0].split('Traceback')[0].strip()} {raised[-1]}".strip()
    return lines[0]


def status(job_id: str, address: str | None = None) -> str:
    """The job's status (PENDING, RUNNING, SUCCEEDED, FAILED, STOPPED)."""
    return str(client(address).get_job_status(job_id).value)


def logs(job_id: str, address: str | None = None) -> str:
    """Everything the job has printed so far."""
    return client(address).get_job_logs(job_id)


def stop(job_id: str, address: str | None = None) -> bool:
    """Ask the cluster to stop the job; whether it was still running."""
    return bool(client(address).stop_job(job_id))


def wait(job_id: str, address: str | None = None, timeout_s: float = 3600.0, echo: Callable[[str], None] = print) -> str:
    """Follow the job's new log lines until it ends (or ``timeout_s``, a positive number of seconds); returns its final status."""
    check_timeout(timeout_s, "--timeout")
    c = client(address)
    seen = 0
    t0 = time.perf_counter()
    while True:
        state = str(c.get_job_status(job_id).value)
        text = c.get_job_logs(job_id)
        if len(text) > seen:
            echo(text[seen:].rstrip("\n"))
            seen = len(text)
        if state in TERMINAL:
            return state
        if time.perf_counter() - t0 > timeout_s:
            raise ValueError(f"job {job_id} still {state} after {timeout_s:.0f} s")
        time.sleep(2.0)
