"""Run one benchmark against several checkouts side by side: one worker process per tree, called in turn.

A benchmark script calls :func:`serve` when started with ``--worker`` and, in its parent process,
:class:`TreeWorker` for each tree (this checkout and e.g. ``--tree /path/to/an/old/worktree``). A
worker imports ``coin_app`` from its tree only (``PYTHONPATH`` = the tree) and the benchmark's own
code from this script's folder, so the same measurement code times both trees. The parent sends one
request at a time and waits for its answer, so the workers never run at once and a change in the
machine's load hits every tree alike when the parent alternates between them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import coin_app

MARK = "@@tree-worker@@ "  # prefix of the worker's answers on stdout (anything else there is log noise)
THIS_TREE = Path(__file__).resolve().parents[1]


def tree_path(value: str) -> Path:
    """``value`` as a checkout root holding ``coin_app/``; SystemExit with one line naming it otherwise."""
    path = Path(value).expanduser().resolve()
    if not (path / "coin_app" / "__init__.py").is_file():
        raise SystemExit(f"bad --tree {value!r}: no coin_app package there; allowed: the root of a coin_app checkout")
    return path


class TreeWorker:
    """A worker process of ``script`` whose ``coin_app`` is the one in ``tree``."""

    def __init__(self, script: str, tree: Path, label: str) -> None:
        self.tree, self.label = tree, label
        env = {**os.environ, "PYTHONPATH": str(tree)}
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env.setdefault(var, "1")
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(script).resolve()), "--worker"],
            cwd=tree,
            env=env,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            bufsize=1,
        )
        where = self.call(op="where")["coin_app"]
        if not Path(where).resolve().is_relative_to(tree):
            self.close()
            raise SystemExit(f"worker for {tree} imported coin_app from {where}")

    def call(self, **request: Any) -> dict[str, Any]:
        """Send one request and return the worker's answer (RuntimeError with its traceback if it failed)."""
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps(request) + "\n")
        self.proc.stdin.flush()
        for line in self.proc.stdout:
            if line.startswith(MARK):
                answer = json.loads(line[len(MARK) :])
                if "error" in answer:
                    raise RuntimeError(f"worker {self.label} ({self.tree}) failed on {request}:\n{answer['error']}")
                return answer
        raise RuntimeError(f"worker {self.label} ({self.tree}) exited with code {self.proc.wait()} on {request}")

    def close(self) -> None:
        """End the worker (it exits when its stdin closes)."""
        if self.proc.poll() is None:
            assert self.proc.stdin is not None
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()


def serve(handle: Callable[[dict[str, Any]], dict[str, Any]]) -> None:
    """The worker's loop: one JSON request per stdin line, ``handle``'s answer (or the error) as one marked stdout line."""
    for line in sys.stdin:
        request = json.loads(line)
        try:
            answer = {"coin_app": coin_app.__file__} if request.get("op") == "where" else handle(request)
        except Exception:  # the parent reports it with the request
            answer = {"error": traceback.format_exc()}
        print(MARK + json.dumps(answer), flush=True)
