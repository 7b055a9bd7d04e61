"""Same seeds => same evaluation episodes, in separate processes with different BLAS thread counts and hash seeds.

At 30 vehicles a policy's actions changed in their last bits (OpenBLAS splits a product among its threads
differently for another thread count) turn into a different episode within 100 steps: the evaluator runs the
policy on one BLAS thread (``coin_app/evaluation/evaluate.py``). Each process evaluates a fixed numpy actor of
the COIN authors' width (three hidden layers of 256: products big enough for OpenBLAS to share among threads)
for a few hundred steps at the paper's density; the per-episode metrics (mean returns included, which any
drift changes) must match exactly. Without the one-thread rule the native pair differs in its mean return.
"""

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from coin_app.backends.metadrive import metadrive_available

SCRIPT = """
import json, sys
import numpy as np
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.inference import NumpyPolicy
from coin_app.sim.config import make_config
backend, steps = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(0)
sizes = [91, 256, 256, 256, 2]
weights = [rng.normal(0, 1 / np.sqrt(n_in), (n_out, n_in)) for n_in, n_out in zip(sizes, sizes[1:])]
biases = [np.zeros(256), np.zeros(256), np.zeros(256), np.array([0.0, 0.5])]  # throttle on: the vehicles meet
policy = NumpyPolicy(weights, biases, ["relu", "relu", "relu", "tanh"])
config = make_config("intersection", "metadrive_compat", backend=backend, num_agents=30)
print("RESULT", json.dumps(evaluate_policy(policy, config, [1000], max_steps=steps)))
"""


def run_twice(backend: str, steps: int) -> list[list[dict]]:
    """The metrics of the same episode from two processes, side by side: 1 and 2 BLAS threads, hash seeds 1 and 2."""
    procs, logs = [], []
    try:
        for threads in (1, 2):
            env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "PYTHONHASHSEED": str(threads)}
            env |= {"OPENBLAS_NUM_THREADS": str(threads), "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
            out, err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")  # files, not pipes: neither process blocks
            logs.append((out, err))
            procs.append(subprocess.Popen([sys.executable, "-c", SCRIPT, backend, str(steps)], env=env, stdout=out, stderr=err, text=True))
        results = []
        for proc, (out, err) in zip(procs, logs, strict=True):
            proc.wait(timeout=900)
            out.seek(0), err.seek(0)
            lines = [line for line in out.read().splitlines() if line.startswith("RESULT ")]
            assert proc.returncode == 0 and len(lines) == 1, err.read()[-2000:]
            results.append(json.loads(lines[0].removeprefix("RESULT ")))
        return results
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for out, err in logs:
            out.close(), err.close()


def test_native_episodes_repeat_across_processes_and_thread_counts():
    first, second = run_twice("native", 400)
    assert first == second
    assert first[0]["num_vehicles"] > 30  # vehicles finished and respawned: the episode is not a trivial one


@pytest.mark.skipif(not metadrive_available(), reason="the optional MetaDrive extra is not installed (requirements-metadrive.txt)")
def test_metadrive_episodes_repeat_across_processes_and_thread_counts():
    first, second = run_twice("metadrive", 300)
    assert first == second
    assert first[0]["num_vehicles"] > 30
