"""cluster/: the launcher config and the RayJob manifest are valid; submit / job against a real local head."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import ray
import yaml

from cluster import jobs
from coin_app.cli import build_parser, main
from coin_app.evaluation.sweep_results import load_trials

REPO = Path(__file__).resolve().parent.parent


def test_cluster_launcher_config_passes_rays_schema():
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = yaml.safe_load((REPO / "cluster" / "cluster.yaml").read_text())
    validate_config(config)  # raises on any schema violation
    validate_config(prepare_config(config))  # and with Ray's defaults filled in, as `ray up` does
    types = config["available_node_types"]
    assert types["cpu_worker"]["min_workers"] == 0 and types["cpu_worker"]["max_workers"] >= 1  # autoscaling CPU workers
    assert config["head_node_type"] == "head" and types["head"]["resources"] == {"CPU": 0}
    assert any("requirements.txt" in c for c in config["setup_commands"])
    assert config["max_workers"] >= sum(t.get("max_workers", 0) for t in types.values())  # every group can reach its max


def test_cluster_launcher_has_an_autoscaling_gpu_learner_node_with_cuda_torch():
    config = yaml.safe_load((REPO / "cluster" / "cluster.yaml").read_text())
    gpu = config["available_node_types"]["gpu_learner"]
    assert gpu["min_workers"] == 0 and gpu["max_workers"] >= 1  # started only for trials that ask for a GPU
    assert gpu["resources"]["GPU"] == 1 and gpu["resources"]["CPU"] >= 1  # what the autoscaler matches GPU bundles against
    assert gpu["node_config"]["InstanceType"].startswith(("g", "p"))  # an AWS GPU instance family
    # after the common setup (CPU torch), the GPU node swaps in the CUDA build of the pinned torch
    (swap,) = gpu["worker_setup_commands"]
    assert "download.pytorch.org/whl/cu" in swap and "torch==2.13.0" in swap and "torch.version.cuda" in swap
    assert "torch==2.13.0" in (REPO / "requirements.txt").read_text()
    cpu = config["available_node_types"]["cpu_worker"]
    assert "GPU" not in cpu["resources"] and "worker_setup_commands" not in cpu  # CPU workers unchanged


def _worker_groups(spec: dict) -> dict:
    return {g["groupName"]: g for g in spec["rayClusterSpec"]["workerGroupSpecs"]}


def test_rayjob_has_cpu_and_gpu_worker_groups_and_one_torch_thread():
    manifest = yaml.safe_load((REPO / "cluster" / "rayjob.yaml").read_text())
    spec = manifest["spec"]
    assert yaml.safe_load(spec["runtimeEnvYAML"])["env_vars"]["OMP_NUM_THREADS"] == "1"
    groups = _worker_groups(spec)
    assert set(groups) == {"cpu-workers", "gpu-workers"}
    cpu, gpu = (groups[n]["template"]["spec"]["containers"][0] for n in ("cpu-workers", "gpu-workers"))
    assert groups["cpu-workers"]["minReplicas"] == 0 and groups["cpu-workers"]["maxReplicas"] >= 1
    assert "nvidia.com/gpu" not in cpu["resources"]["limits"]
    g = groups["gpu-workers"]
    assert g["minReplicas"] == 0 and g["replicas"] == 0 and g["maxReplicas"] >= 1  # scales up only for GPU trials
    limits, requests = gpu["resources"]["limits"], gpu["resources"]["requests"]
    assert str(limits["nvidia.com/gpu"]) == "1" and requests == limits  # KubeRay advertises the limit to Ray as 1 GPU
    assert gpu["image"] != cpu["image"] and "cuda" in gpu["image"]  # the CUDA-torch build of cluster/Dockerfile
    assert {m["mountPath"] for m in gpu["volumeMounts"]} == {"/results"}
    tolerations = groups["gpu-workers"]["template"]["spec"]["tolerations"]
    assert any(t["key"] == "nvidia.com/gpu" for t in tolerations)
    dockerfile = (REPO / "cluster" / "Dockerfile").read_text()
    assert "ARG TORCH_INDEX=https://download.pytorch.org/whl/cpu" in dockerfile and "${TORCH_INDEX}" in dockerfile


def test_documented_gpu_sweep_command_parses_and_reserves_one_gpu_per_trial():
    from coin_app.algorithms.checks import parse_overrides
    from tuning import get_experiment
    from tuning.experiment import expand_grid
    from tuning.trainable import trial_resources

    text = (REPO / "cluster" / "rayjob.yaml").read_text()
    (line,) = [ln for ln in text.splitlines() if ln.startswith("#   entrypoint:")]
    words = line.split("entrypoint:", 1)[1].split()
    assert words[:3] == ["python", "-m", "coin_app"]
    args = build_parser().parse_args(words[3:])
    assert args.command == "sweep" and args.storage.startswith("/results")
    overrides = parse_overrides(args.set)  # as the sweep command reads them
    assert overrides == {"num_learners": 1, "num_gpus_per_learner": 1}
    doc = (REPO / "docs" / "cluster.md").read_text()
    assert "--set num_learners=1 num_gpus_per_learner=1" in doc
    space = get_experiment(args.experiment).param_space(args.scenario, overrides=overrides)
    for trial in expand_grid(space):
        bundles = trial_resources(trial).bundles
        assert sum(b.get("GPU", 0) for b in bundles) == 1 and bundles[0].get("GPU", 0) == 0  # the learner's own bundle


def test_rayjob_manifest_runs_a_real_coin_app_command_on_the_pinned_ray():
    manifest = yaml.safe_load((REPO / "cluster" / "rayjob.yaml").read_text())
    assert manifest["apiVersion"] == "ray.io/v1" and manifest["kind"] == "RayJob"
    spec = manifest["spec"]
    assert spec["rayClusterSpec"]["rayVersion"] == ray.__version__
    words = spec["entrypoint"].split()
    assert words[:3] == ["python", "-m", "coin_app"]
    args = build_parser().parse_args(words[3:])  # the entrypoint is a command our CLI accepts
    assert args.command == "sweep" and args.storage.startswith("/results")
    mounts = {m["mountPath"] for m in spec["rayClusterSpec"]["headGroupSpec"]["template"]["spec"]["containers"][0]["volumeMounts"]}
    assert "/results" in mounts
    assert "requirements.txt" in (REPO / "cluster" / "Dockerfile").read_text()


def test_runtime_env_carries_the_repo_and_its_exact_pins():
    env = jobs.runtime_env("pip")
    assert env["working_dir"] == str(REPO) and ".venv" in env["excludes"] and "runs" in env["excludes"]
    pins = env["pip"]["packages"]
    assert "ray[default,rllib]==2.60.0" in pins and "torch==2.13.0" in pins
    assert all("==" in p for p in pins) and len(pins) == sum("==" in ln for ln in (REPO / "requirements.txt").read_text().splitlines())
    assert "pip" not in jobs.runtime_env("none")
    with pytest.raises(ValueError, match="bad install mode 'conda'; allowed: pip, none"):
        jobs.runtime_env("conda")


def test_submit_refuses_bad_input_before_contacting_anything(capsys):
    assert main(["submit", "--address", "http://127.0.0.1:1", "--", "sweep", "seeds", "--smoke"]) == 2
    assert "cannot reach a Ray job server at http://127.0.0.1:1" in capsys.readouterr().err
    assert main(["submit", "--address", "127.0.0.1:8265", "--", "sweep", "seeds"]) == 2
    assert "bad --address '127.0.0.1:8265'" in capsys.readouterr().err
    assert main(["submit", "--", "fly", "--to", "mars"]) == 2
    assert "bad coin_app command 'fly --to mars'" in capsys.readouterr().err
    assert main(["submit"]) == 2
    assert "nothing to submit" in capsys.readouterr().err


def test_a_refused_submission_names_the_servers_reason_in_one_line(monkeypatch, capsys):
    """The job server answers a taken submission id with its own traceback (status 500): the line gives its last line."""
    from cluster import jobs

    reason = "ValueError: Job with submission_id twice already exists. Please use a different submission_id."
    answer = f'Request failed with status code 500: Traceback (most recent call last):\n  File "x.py", line 1, in f\n{reason}\n'

    class Server:
        def submit_job(self, **kwargs):
            raise RuntimeError(answer)

    monkeypatch.setattr(jobs, "client", lambda address: Server())
    argv = ["submit", "--install", "none", "--submission-id", "twice", "--", "scenarios"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.strip().endswith(f"refused the job: Request failed with status code 500: {reason}"), err
    assert jobs.server_reason(RuntimeError("plain reason\nmore")) == "plain reason"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def local_head(tmp_path_factory):
    """A real Ray head on 127.0.0.1 (``ray start --head --block``, job server included), killed afterwards.

    ``--block`` keeps ``ray start`` in the foreground of its own process group, so the fixture
    stops exactly this head (and its raylet, GCS, dashboard) without ``ray stop``, which would
    stop every Ray on the machine; its own ``--temp-dir`` keeps its address file from making
    later ``ray.init()`` calls on this machine connect to it.
    """
    if ray.is_initialized():
        ray.shutdown()
    port, dash = _free_port(), _free_port()
    bindir = str(Path(sys.executable).parent)
    env = {**os.environ, "PATH": f"{bindir}:{os.environ['PATH']}", "PYTHONPATH": "", "RAY_USAGE_STATS_ENABLED": "0", "OMP_NUM_THREADS": "1"}
    start = [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block", "--node-ip-address=127.0.0.1", f"--port={port}"]
    start += ["--num-cpus=2", "--include-dashboard=true", "--dashboard-host=127.0.0.1", f"--dashboard-port={dash}", "--disable-usage-stats"]
    # every other fixed default port free too, so the head coexists with any other Ray on the machine
    for flag in ("dashboard-agent-listen-port", "dashboard-agent-grpc-port", "runtime-env-agent-port", "metrics-export-port"):
        start.append(f"--{flag}={_free_port()}")
    start += [f"--ray-client-server-port={_free_port()}", f"--node-manager-port={_free_port()}", f"--object-manager-port={_free_port()}"]
    temp_dir = tempfile.mkdtemp(prefix="rayhead", dir="/tmp")  # its own temp dir: short socket paths, and its
    start.append(f"--temp-dir={temp_dir}")  # ray_current_cluster file never redirects other ray.init() calls
    log = open(tmp_path_factory.mktemp("head") / "head.log", "w")
    head = subprocess.Popen(start, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    address = f"http://127.0.0.1:{dash}"
    try:
        deadline = time.time() + 180
        while True:  # ready once the job server answers
            try:
                jobs.client(address).list_jobs()
                break
            except Exception:
                if head.poll() is not None or time.time() > deadline:
                    raise
                time.sleep(1.0)
        yield address
    finally:
        for sig, grace in ((signal.SIGTERM, 5), (signal.SIGKILL, 30)):  # `ray start --block` rarely exits on SIGTERM in 30 s
            try:
                os.killpg(head.pid, sig)
            except ProcessLookupError:
                break
            try:
                head.wait(timeout=grace)
                break
            except subprocess.TimeoutExpired:
                continue
        log.close()
        shutil.rmtree(temp_dir, ignore_errors=True)


def test_submit_a_smoke_sweep_to_a_local_head_and_follow_it(local_head, tmp_path, capsys):
    storage = tmp_path / "results"
    argv = ["submit", "--address", local_head, "--install", "none", "--submission-id", "coin-smoke-1", "--wait", "--timeout", "900"]
    argv += ["--", "sweep", "seeds", "--smoke", "--seeds", "0", "--steps", "500", "--storage", str(storage)]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "submitted job coin-smoke-1" in out and "ended: SUCCEEDED" in out and "sweep summary:" in out
    trials = load_trials(storage / "seeds-intersection-smoke")
    assert [t.name for t in trials] == ["cig_td3-s0"] and trials[0].finished and trials[0].final_checkpoint is not None
    assert json.loads((storage / "seeds-intersection-smoke" / "coin_sweep.json").read_text())["trials"] == 1
    # the pass-throughs
    assert main(["job", "status", "coin-smoke-1", "--address", local_head]) == 0
    assert capsys.readouterr().out.strip() == "SUCCEEDED"
    assert main(["job", "logs", "coin-smoke-1", "--address", local_head]) == 0
    assert "sweep summary:" in capsys.readouterr().out
    assert main(["job", "stop", "coin-smoke-1", "--address", local_head]) == 0
    assert "was not running" in capsys.readouterr().out
    assert main(["job", "status", "no-such-job", "--address", local_head]) == 2
    assert "no-such-job" in capsys.readouterr().err
