"""Table-driven: every user-facing command given bad input ends in one clear line (exit 2), never a traceback, before any work."""

import json
import math
import zipfile

import numpy as np
import pytest

from coin_app.algorithms import registry
from coin_app.cli import main, one_line
from coin_app.inference import export_policy

# (argv, a phrase the one line must contain); paths under a regular file cannot be created, even by root
CASES = [
    (["train", "--algo", "sac"], "invalid choice: 'sac'"),
    (["train", "--set", "tau=inf"], "bad value for 'tau': inf; allowed: a finite number in (0, 1]"),
    (["train", "--set", "tau=abc"], "bad value for 'tau': 'abc'"),
    (["train", "--set", "actor_lr=nan"], "bad value for 'actor_lr': nan"),
    (["train", "--set", "exploration_noise=-inf"], "bad value for 'exploration_noise': -inf"),
    (["train", "--set", "updates_per_env_step=0"], "bad value for 'updates_per_env_step': 0"),
    (["train", "--set", "global_weight=nan"], "bad value for 'global_weight'"),
    (["train", "--algo", "ippo", "--set", "lr=inf"], "bad value for 'lr': inf"),
    (["train", "--algo", "ippo", "--set", "gamma=1.5"], "bad value for 'gamma': 1.5; allowed: a finite number in [0, 1]"),
    (["train", "--algo", "ippo", "--set", "clip_param=nan"], "bad value for 'clip_param'"),
    (["train", "--algo", "ippo", "--set", "num_epochs=0"], "bad value for 'num_epochs': 0; allowed: an integer >= 1"),
    (["train", "--algo", "copo", "--set", "initial_lcf_mean=2"], "bad value for 'initial_lcf_mean'"),
    (["train", "--set", "hidden=64.5"], "bad value for 'hidden': 64.5; allowed: an integer >= 1"),
    (["train", "--set", "global_critic=1"], "bad value for 'global_critic': 1; allowed: True or False"),
    (["train", "--set", "horizon=inf"], "horizon"),
    (["train", "--seed", "100001"], "bad seed 100001"),
    (["train", "--steps", "0"], "bad steps 0"),
    (["train", "--threads", "0"], "bad threads 0"),
    (["train", "--out", "{file}/run"], "cannot write the run directory"),
    (["train", "--resume", "{missing}"], "does not exist"),
    (["evaluate", "{missing}"], "does not exist"),
    (["evaluate", "{truncated_npz}"], "BadZipFile"),
    (["evaluate", "{file}"], "no known policy suffix"),
    (["evaluate", "{good_npz}", "--out", "{good_npz}"], "bad --out"),  # the results would overwrite the policy
    (["evaluate", "{good_npz}", "--replay", "{good_npz}"], "bad --replay"),
    (["evaluate", "{good_npz}", "--seeds", "200000", "200000"], "given more than once"),
    (["evaluate", "{missing}", "--preset", "mdc"], "unknown preset 'mdc'; allowed: paper, metadrive_compat, kinematic"),
    (["export", "{missing}", "--out", "x.npz"], "does not exist"),
    (["export", "{missing}", "--format", "tflite", "--out", "x.tflite"], "unknown format 'tflite'"),
    (["evaluate-arena", "heuristic", "--cases", "4x"], "bad case"),
    (["sweep", "nope"], "nope"),
    (["demo", "--steps", "0"], "--steps"),
    # issue 60: conflicting values for one key, outputs over inputs, bounds, waits
    (["train", "--num-agents", "4", "--set", "num_agents=8"], "--num-agents 4 and --set num_agents=8 set one key to two values"),
    (["train", "--set", "horizon=40", "horizon=50"], "--set gives horizon twice (40 and 50)"),
    # repeated --set groups add up, so one key across two groups is one key twice (every command that takes --set)
    (["train", "--set", "horizon=40", "--set", "horizon=50"], "--set gives horizon twice (40 and 50); allowed: one value per key"),
    (["evaluate", "{good_npz}", "--set", "horizon=40", "--set", "horizon=50"], "--set gives horizon twice (40 and 50)"),
    (["demo", "--out", "{tmp}/run", "--set", "horizon=40", "--set", "horizon=50"], "--set gives horizon twice (40 and 50)"),
    (["sweep", "seeds", "--smoke", "--set", "tau=0.1", "--set", "tau=0.2"], "--set gives tau twice (0.1 and 0.2)"),
    (["config", "--set", "tau=0.1", "--set", "tau=0.2"], "--set gives tau twice (0.1 and 0.2)"),
    (["demo", "--out", "{tmp}/run", "--num-agents", "4", "--set", "num_agents=8"], "--num-agents 4 and --set num_agents=8 set one"),
    (["config", "--num-agents", "4", "--set", "num_agents=8"], "--num-agents 4 and --set num_agents=8 set one key to two values"),
    (["train", "--connect-timeout", "-1"], "bad --connect-timeout -1.0; allowed: a finite number of seconds > 0"),
    (
        ["train", "--address", "127.0.0.1:1", "--connect-timeout", "2"],
        "cannot reach a Ray cluster at 127.0.0.1:1 within --connect-timeout 2 s",
    ),
    (["evaluate", "{good_npz}", "--out", "{dir}"], "it is a directory; allowed: a file path"),  # refused before evaluating
    (["evaluate", "{good_npz}", "--episodes", "100000"], "bad --episodes 100000; allowed: an integer from 1 to 1000"),
    (["evaluate", "{good_npz}", "--num-agents", "4", "--set", "num_agents=3"], "set one key to two values"),
    (["evaluate", "{bottleneck_npz}", "--backend", "metadrive"], "reads 91 observation numbers (bottleneck, native backend"),
    (["export", "{missing}", "--out", "{missing}/p.npz"], "is, or is inside, the checkpoint it exports"),
    (
        ["pair", "{good_npz}", "{good_npz}", "--out", "{tmp}/pair.json"],
        "the long-range policy was trained on 'intersection', not the arena",
    ),
    (["pair", "{good_npz}", "{good_npz}", "--out", "{good_npz}"], "is, or is inside, a policy it pairs"),
    (["evaluate-arena", "heuristic", "--cases", "100000x1"], "bad case '100000x1'; allowed: 1 to 64 vehicles and 0 to 64 obstacles"),
    (
        ["evaluate-arena", "heuristic", "--scenarios-per-case", "100000"],
        "bad --scenarios-per-case 100000; allowed: an integer from 1 to 10000",
    ),
    (["evaluate-arena", "heuristic", "--out", "{file}"], "it is a file"),
    (["submit", "--wait", "--timeout", "-1", "--", "scenarios"], "bad --timeout -1.0; allowed: a finite number of seconds > 0"),
    (["sweep", "seeds", "--smoke", "--connect-timeout", "0"], "bad --connect-timeout 0.0"),
    (["sweep", "seeds", "--smoke", "--accept-changes"], "--accept-changes without --resume"),
]


@pytest.fixture
def paths(tmp_path):
    """Paths the cases refer to: a missing one, a regular file, a truncated exported policy."""
    file = tmp_path / "plain.txt"
    file.write_text("not a directory")
    good = export_policy(_tiny_actor(), tmp_path / "good.npz", "numpy", meta={"scenario": "intersection"})
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    bottleneck = export_policy(_tiny_actor(), tmp_path / "bottleneck.npz", "numpy", meta={"scenario": "bottleneck", "env_config": {}})
    (tmp_path / "adir").mkdir()
    return {
        "missing": str(tmp_path / "missing"),
        "file": str(file),
        "truncated_npz": str(truncated),
        "good_npz": str(good),
        "bottleneck_npz": str(bottleneck),
        "dir": str(tmp_path / "adir"),
        "tmp": str(tmp_path),
    }


def _tiny_actor():
    import torch

    return torch.nn.Sequential(torch.nn.Linear(91, 4), torch.nn.Tanh(), torch.nn.Linear(4, 2), torch.nn.Tanh())


@pytest.mark.parametrize(("argv", "phrase"), CASES, ids=[" ".join(c[0])[:60] for c in CASES])
def test_bad_input_ends_in_one_clear_line(argv, phrase, paths, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = [a.format(**paths) for a in argv]
    if argv[0] == "train" and "--out" not in argv:
        argv += ["--out", str(tmp_path / "run")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    assert phrase in err, err
    assert not (tmp_path / "run").exists()  # refused before any work


@pytest.mark.parametrize("name", sorted(registry.ALGORITHMS))
def test_every_algorithm_key_refuses_inf_nan_and_wrong_types_through_train(name, capsys, tmp_path):
    scenario = registry.get(name).scenarios[0]
    for key in registry.get(name).hyperparameters:
        rule = registry.get(name).rule(key)
        for raw in ("inf", "nan", "'abc'", "[1]"):
            if rule.kind == "choice" and raw == "'abc'":
                raw = "'abc-not-a-choice'"
            code = main(["train", "--algo", name, "--scenario", scenario, "--set", f"{key}={raw}", "--out", str(tmp_path / "r")])
            err = capsys.readouterr().err
            assert code == 2 and err.count("\n") == 1 and f"bad value for {key!r}" in err and "allowed: " in err, (key, raw, err)
    assert not (tmp_path / "r").exists()


def test_evaluate_warns_on_training_and_validation_seeds(tmp_path, capsys):
    policy = export_policy(_tiny_actor(), tmp_path / "p.npz", "numpy", meta={"scenario": "intersection"})
    assert main(["evaluate", str(policy), "--seeds", "3", "100002", "--set", "num_agents=2", "horizon=5"]) == 0
    err = capsys.readouterr().err
    assert "warning: --seeds [3, 100002] are training or validation seeds" in err
    assert main(["evaluate", str(policy), "--seeds", "200001", "--set", "num_agents=2", "horizon=5"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_one_line_of_any_exception():
    assert one_line(ValueError("bad x\nsecond line")) == "bad x"
    assert one_line(zipfile.BadZipFile("File is not a zip file")) == "BadZipFile: File is not a zip file"
    assert (
        one_line(FileNotFoundError(2, "No such file or directory", "/x/y"))
        == "FileNotFoundError: [Errno 2] No such file or directory: '/x/y'"
    )
    assert one_line(RuntimeError("")) == "RuntimeError: RuntimeError"
    assert math.isfinite(np.float64(1.0))


@pytest.mark.parametrize(("flag", "package"), [("--wandb", "wandb"), ("--mlflow", "mlflow")])
def test_sweep_tracking_flags_refuse_a_missing_package_before_any_work(flag, package, tmp_path, capsys):
    import importlib.util

    if importlib.util.find_spec(package) is not None:
        pytest.skip(f"{package} is installed")
    assert main(["sweep", "seeds", "--smoke", flag, "x", "--storage", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert f"{flag} x needs the {package} package; allowed: pip install {package}" in err and err.count("\n") == 1
    assert not (tmp_path / "s").exists()


def test_evaluate_never_writes_over_the_policy_it_reads(paths, capsys):
    before = open(paths["good_npz"], "rb").read()
    assert main(["evaluate", paths["good_npz"], "--episodes", "1", "--out", paths["good_npz"]]) == 2
    assert "is, or is inside, the policy it evaluates" in capsys.readouterr().err
    assert open(paths["good_npz"], "rb").read() == before


# ----------------------------------------------------------------------------- the Python API, as strict as the CLI (issue 60)
def _driving(**kw):
    from coin_app.sim.driving_env import DrivingEnv

    return DrivingEnv(**kw)


def _pettingzoo(**kw):
    from coin_app.adapters.pettingzoo_env import CoinParallelEnv

    return CoinParallelEnv(**kw)


def _rllib(**kw):
    from coin_app.adapters.rllib_env import CoinMultiAgentEnv

    return CoinMultiAgentEnv(kw)


ENVS = {"DrivingEnv": _driving, "CoinParallelEnv": _pettingzoo, "CoinMultiAgentEnv": _rllib}
# (what, the call on a reset env, a phrase of the one line every env gives); the phrases come from one shared check
ENV_CASES = [
    ("seed 1.5", lambda env: env.reset(seed=1.5), "bad seed 1.5; allowed: None or an integer >= 0"),
    ("seed -1", lambda env: env.reset(seed=-1), "bad seed -1; allowed: None or an integer >= 0"),
    ("seed True", lambda env: env.reset(seed=True), "bad seed True"),
    ("int key", lambda env: env.step({0: [0.0, 0.0], **{a: [0.0, 0.0] for a in env.agents[1:]}}), "action keys must be agent ids (str)"),
    ("dict action", lambda env: env.step({a: {"steer": 0.0} for a in env.agents}), "must be 2 numbers, got dict"),
    ("nan action", lambda env: env.step({a: [np.nan, 0.0] for a in env.agents}), "holds a non-finite number"),
    ("3 numbers", lambda env: env.step({a: [0.0, 0.0, 0.0] for a in env.agents}), "must have 2 numbers, got shape (3,)"),
    ("unknown agent", lambda env: env.step({"agent99": [0.0, 0.0], **{a: [0.0, 0.0] for a in env.agents}}), "cannot act now"),
    ("a list", lambda env: env.step([[0.0, 0.0]]), "actions must be a dict of agent id -> action, got list"),
]


@pytest.mark.parametrize("make", list(ENVS.values()), ids=list(ENVS))
@pytest.mark.parametrize(("what", "call", "phrase"), ENV_CASES, ids=[c[0] for c in ENV_CASES])
def test_every_env_api_refuses_the_same_bad_input_with_the_same_line(make, what, call, phrase):
    env = make(num_agents=2, horizon=20)
    env.reset(seed=0)
    with pytest.raises(ValueError) as info:
        call(env)
    text = str(info.value)
    assert phrase in text and "\n" not in text, (what, text)


def test_a_config_with_overrides_or_a_string_config_is_refused_never_dropped():
    from coin_app.adapters.pettingzoo_env import CoinParallelEnv
    from coin_app.adapters.rllib_env import CoinMultiAgentEnv
    from coin_app.sim.config import make_config
    from coin_app.sim.driving_env import DrivingEnv

    config = make_config("intersection")
    both = "pass either a config or scenario/preset/overrides, not both"
    for call, given in (
        (lambda: DrivingEnv(config, num_agents=4), "num_agents"),
        (lambda: DrivingEnv(config, scenario="roundabout"), "scenario"),
        (lambda: DrivingEnv(config, preset="kinematic"), "preset"),
        (lambda: CoinParallelEnv(config, num_agents=4), "num_agents"),
        (lambda: CoinMultiAgentEnv({"scenario_config": config, "num_agents": 4}), "num_agents"),
    ):
        with pytest.raises(ValueError, match=f"{both} \\(got a config and {given}\\)"):
            call()
    with pytest.raises(ValueError, match=r"got the string 'roundabout' as its config; allowed: DrivingEnv\(scenario='roundabout'\)"):
        DrivingEnv("roundabout")
    assert DrivingEnv(scenario="roundabout", num_agents=4).config == make_config("roundabout", num_agents=4)  # nothing dropped


@pytest.mark.parametrize("make", list(ENVS.values()), ids=list(ENVS))
def test_numpy_integers_are_the_numbers_they_hold(make):
    env = make(num_agents=np.int64(3), horizon=np.int32(20))
    cfg = getattr(env, "config", None) or env.driving_env.config
    assert cfg.num_agents == 3 and type(cfg.num_agents) is int and cfg.horizon == 20 and type(cfg.horizon) is int
    first, _ = env.reset(seed=np.int64(7))
    again, _ = make(num_agents=3, horizon=20).reset(seed=7)
    assert first.keys() == again.keys() and all(np.array_equal(first[a], again[a]) for a in first)


def test_the_pettingzoo_env_refuses_step_and_reset_after_close():
    env = _pettingzoo(num_agents=2, horizon=20)
    env.reset(seed=0)
    actions = {a: [0.0, 0.5] for a in env.agents}
    env.close()
    for call in (lambda: env.step(actions), lambda: env.reset(seed=0)):
        with pytest.raises(RuntimeError, match=r"the env is closed \(close\(\) was called\); allowed: a new CoinParallelEnv"):
            call()


@pytest.mark.parametrize(("fmt", "suffix"), [("numpy", "npz"), ("torchscript", "pt"), ("onnx", "onnx")])
def test_every_export_format_refuses_a_non_finite_observation(fmt, suffix, tmp_path):
    from coin_app.inference import load_policy

    if fmt == "onnx":
        pytest.importorskip("onnx")
        pytest.importorskip("onnxruntime")
    policy = load_policy(export_policy(_tiny_actor(), tmp_path / f"p.{suffix}", fmt))
    obs = np.full((3, 91), 0.5, np.float32)
    assert np.isfinite(policy(obs)).all()
    for bad, shown in ((np.nan, "nan"), (np.inf, "inf"), (-np.inf, "-inf")):
        broken = obs.copy()
        broken[1, 7] = bad
        with pytest.raises(ValueError, match=rf"observation row 1 holds {shown} at index 7 \(1 row\(s\) non-finite\); allowed: finite"):
            policy(broken)


# ----------------------------------------------------------------------------- one writer per output directory (issue 60)
HOLDER = (
    "import sys, time; from coin_app.evaluation.outputs import OutputLock; "
    "OutputLock(sys.argv[1], 'the holder command').acquire(); print('held', flush=True); time.sleep(600)"
)


def _hold(directory):
    """A process holding ``directory``'s lock (its PID; it prints once it holds it)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(directory)], stdout=subprocess.PIPE, text=True, env=env)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_locked_output_is_refused_naming_its_writer_and_a_dead_writers_lock_is_taken_over(tmp_path, capsys):
    from fixtures import tiny_cli

    from coin_app.evaluation.outputs import OutputLock, lock_path

    out = tmp_path / "run"
    holder = _hold(out)
    try:
        with pytest.raises(ValueError, match=rf"{out} is being written by PID {holder.pid} on .* \(the holder command, since "):
            OutputLock(out).acquire()
        argv = ["train", "--algo", "itd3", *tiny_cli("itd3", "bottleneck"), "--steps", "100", "--out", str(out)]
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"is being written by PID {holder.pid}" in err and "allowed: wait until it ends, or another --out" in err
        assert err.count("\n") == 1 and not out.exists()  # refused before anything was written
    finally:
        holder.kill()  # SIGKILL: no release, its record stays in the lock file
        holder.wait()
    assert json.loads(lock_path(out).read_text())["pid"] == holder.pid
    with OutputLock(out, "the next command") as lock:  # the kernel dropped the dead writer's lock: taken over, and said
        assert f"lock of PID {holder.pid} (the holder command) was stale (that writer is gone); taken over" in lock.stale_note()
        with OutputLock(out) as again:  # reentrant within one process
            assert again.stale_note() is None or again.path == lock.path
        assert json.loads(lock_path(out).read_text())["command"] == "the next command"
    assert not lock_path(out).exists()  # the last release removes it


def test_a_refusal_in_the_moment_between_the_lock_and_its_record_still_names_the_holder(tmp_path):
    """The holder writes its record just after taking the lock: a refusal in between waits for it, not ``PID ?``."""
    import fcntl
    import os
    import threading
    import time

    from coin_app.evaluation.outputs import OutputLock, lock_path

    out = tmp_path / "run"
    out.mkdir()
    fd = os.open(lock_path(out), os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_EX)  # locked, record still empty (as a holder is for a moment)
    record = {"pid": os.getpid(), "host": "h", "command": "the late writer", "started": "now"}
    writer = threading.Timer(0.3, lambda: os.pwrite(fd, json.dumps(record).encode(), 0))
    writer.start()
    try:
        t0 = time.monotonic()
        with pytest.raises(ValueError, match=rf"being written by PID {os.getpid()} on h \(the late writer, since now\)"):
            OutputLock(out).acquire()
        assert time.monotonic() - t0 >= 0.25  # it waited for the record rather than answering from the empty file
    finally:
        writer.join()
        os.close(fd)


def _snapshot(directory):
    """Every file under ``directory`` (relative path -> bytes)."""
    return {str(p.relative_to(directory)): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def test_sweep_refuses_a_live_writer_of_its_directory_and_takes_a_dead_ones_lock_over(tmp_path, capsys):
    from coin_app.evaluation.outputs import lock_path

    storage, name = tmp_path / "sweeps", "s"
    path = storage / name
    holder = _hold(path)
    argv = ["sweep", "seeds", "--smoke", "--storage", str(storage), "--name", name]
    try:
        assert main(argv) == 2
        captured = capsys.readouterr()
        assert captured.err.count("\n") == 1 and captured.out == ""
        assert captured.err.startswith(f"error: {path} is being written by PID {holder.pid} on ")
        assert (
            "(the holder command, since " in captured.err and "allowed: wait until it ends, or another --name or --storage" in captured.err
        )
        assert not path.exists()  # refused before Ray or Tune touched it
    finally:
        holder.kill()  # SIGKILL: its record stays in the lock file, the kernel drops its lock
        holder.wait()
    assert json.loads(lock_path(path).read_text())["pid"] == holder.pid
    # the next driver takes the dead one's lock over (and says so); here it goes on to refuse an empty --resume, Ray-free
    assert main([*argv, "--resume"]) == 2
    captured = capsys.readouterr()
    assert f"lock of PID {holder.pid} (the holder command) was stale (that writer is gone); taken over" in captured.out
    assert captured.err.startswith(f"error: nothing to resume at {path}") and captured.err.count("\n") == 1
    assert not lock_path(path).exists() and not path.exists()  # released on the way out; nothing written


def test_report_refuses_a_live_writer_of_its_directory_and_takes_a_dead_ones_lock_over(tmp_path, capsys):
    from coin_app.evaluation.outputs import OUTPUTS_INDEX, lock_path

    table = _results_table(tmp_path / "results.csv")
    out = tmp_path / "report"
    out.mkdir()
    (out / "report.html").write_text("an earlier report's page")
    (out / OUTPUTS_INDEX).write_text(json.dumps(["report.html"]))
    argv = ["report", str(table), "--out", str(out), "--tsne-samples", "40", "--tsne-episodes", "1"]
    holder = _hold(out)
    before = _snapshot(tmp_path)  # the table, the earlier report and the holder's lock file
    try:
        assert main(argv) == 2
        captured = capsys.readouterr()
        assert captured.err.count("\n") == 1 and captured.out == ""
        assert captured.err.startswith(f"error: {out} is being written by PID {holder.pid} on ")
        assert "(the holder command, since " in captured.err and "allowed: wait until it ends, or another --out" in captured.err
        assert _snapshot(tmp_path) == before  # the earlier report as it was, nothing staged beside it
    finally:
        holder.kill()
        holder.wait()
    assert main(argv) in (0, 1)  # 1: the made-up checkpoints have no learning curves (listed as unreadable)
    text = capsys.readouterr().out
    assert f"lock of PID {holder.pid} (the holder command) was stale (that writer is gone); taken over" in text
    assert (out / "report.html").read_text() != "an earlier report's page" and (out / "results.csv").is_file()
    assert not lock_path(out).exists()


def test_a_report_is_replaced_as_one_set_and_an_interrupted_one_leaves_the_old_as_it_was(tmp_path, monkeypatch, capsys):
    from coin_app.evaluation import report
    from coin_app.evaluation.outputs import OUTPUTS_INDEX

    table = _results_table(tmp_path / "results.csv")
    out = tmp_path / "report"
    out.mkdir()
    (out / "notes.md").write_text("the user's own file")  # not the report's: it stays through every report
    argv = ["report", str(table), "--out", str(out), "--tsne-samples", "40", "--tsne-episodes", "1"]
    assert main(argv) in (0, 1)  # 1: the made-up checkpoints have no learning curves (listed as unreadable)
    written = json.loads((out / OUTPUTS_INDEX).read_text())
    assert "report.html" in written and "results.csv" in written and "notes.md" not in written
    (out / "old_figure.png").write_bytes(b"a figure the previous report drew")  # as if that report had written it:
    (out / OUTPUTS_INDEX).write_text(json.dumps([*written, "old_figure.png"]))
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def killed(*args, **kwargs):
        raise KeyboardInterrupt("killed while writing the page")

    monkeypatch.setattr(report, "write_html", killed)
    assert main(argv) == 130
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # the old report, byte for byte
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".report.")]  # no staging left behind
    monkeypatch.undo()
    capsys.readouterr()
    assert main(argv) in (0, 1)
    assert not (out / "old_figure.png").exists() and (out / "report.html").is_file()  # none of the old report's files left
    assert (out / "notes.md").read_text() == "the user's own file"


# a real `report` that SIGKILLs itself after the k-th rename of its swap (an old entry aside, or a new one in): a kill -9
# at a known point of the swap, with the process, its lock and the disk as a kill leaves them
KILLED_REPORT = """
import os, signal, sys
from pathlib import Path
from coin_app.cli import main
out, at, real, moved = Path(sys.argv[1]).absolute(), int(sys.argv[2]), os.replace, [0]
def replace(src, dst):
    real(src, dst)
    src, dst = Path(src), Path(dst)
    if (src.parent == out and '.old-' in dst.parent.name) or ('.staged-' in src.parent.name and dst.parent == out):
        moved[0] += 1
        if moved[0] == at:
            os.kill(os.getpid(), signal.SIGKILL)
os.replace = replace
main(sys.argv[3:])
"""


def test_report_killed_with_sigkill_in_its_swap_leaves_the_old_report_whole_and_the_next_report_a_whole_new_one(tmp_path, capsys):
    import os
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from coin_app.evaluation.outputs import OUTPUTS_INDEX, lock_path, recover_swaps

    work = tmp_path / "work"
    work.mkdir()
    table = _results_table(work / "results.csv")
    out = work / "report"
    out.mkdir()
    old = {"report.html": b"the old page", "results.csv": b"the old table", "old_figure.png": b"a figure only the old one drew"}
    for name, data in old.items():
        (out / name).write_bytes(data)
    (out / OUTPUTS_INDEX).write_text(json.dumps(sorted(old)))
    (out / "notes.md").write_text("the user's own file")
    before = _snapshot(out)
    argv = ["report", str(table), "--out", str(out), "--tsne-samples", "40", "--tsne-episodes", "1"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    at = len(old) + 2  # every old entry aside, two new ones in: the middle of the swap
    proc = subprocess.Popen([sys.executable, "-c", KILLED_REPORT, str(out), str(at), *argv], env=env, stderr=subprocess.PIPE, text=True)
    err = proc.communicate(timeout=600)[1]
    assert proc.returncode == -9, err[-2000:]
    aside = work / f".report.old-{proc.pid}"
    assert _snapshot(out) != before  # killed inside the swap: the report directory is half-swapped
    assert {n: (aside / n).read_bytes() for n in old} == old  # the old report whole, beside it, until the next report
    assert json.loads(lock_path(out).read_text())["pid"] == proc.pid  # its lock record stays; the kernel dropped the lock
    # what a recovery makes of exactly this disk state (on a copy): the old report, byte for byte, and nothing staged
    copy = tmp_path / "copy"
    shutil.copytree(work, copy)
    assert recover_swaps(copy / "report") == [aside.name]
    assert _snapshot(copy / "report") == before and sorted(p.name for p in copy.iterdir() if p.name.startswith(".report.")) == [
        ".report.lock"
    ]
    # the next report takes the dead one's lock over, rolls its swap back, and swaps a whole new report in
    assert main(argv) in (0, 1)  # 1: the made-up checkpoints have no learning curves (listed as unreadable)
    note = f"report's lock of PID {proc.pid} (python -m coin_app {' '.join(argv)}) was stale (that writer is gone); taken over"
    assert note in capsys.readouterr().out
    written = json.loads((out / OUTPUTS_INDEX).read_text())
    assert sorted(p.name for p in out.iterdir()) == sorted([*written, OUTPUTS_INDEX, "notes.md"])
    assert "report.html" in written and "old_figure.png" not in written and (out / "notes.md").read_text() == "the user's own file"
    assert (out / "results.csv").read_bytes() != old["results.csv"] and (out / "report.html").read_bytes() != old["report.html"]
    assert [p.name for p in work.iterdir() if p.name.startswith(".report.")] == []  # no staging, no aside, no lock left


def test_a_swap_killed_half_way_is_rolled_back_to_the_old_outputs_whole(tmp_path):
    """A kill between the renames of a swap (``staged_outputs``), crafted as it leaves the disk: the next build's recovery
    puts every old entry back and takes every new one out, whatever the point of the kill."""
    from coin_app.evaluation.outputs import OUTPUTS_INDEX, SWAP_RECORD, recover_swaps

    old, new = {"a.csv": b"old a", "b.png": b"old b"}, {"a.csv": b"new a", "c.md": b"new c"}
    dead = 2**22 + 12345  # a PID no process has (above the kernel's default pid_max)
    for moved_in in range(len(new) + 1):  # how many new entries had moved in when it was killed
        root = tmp_path / str(moved_in)
        out, stage, aside = root / "report", root / f".report.staged-{dead}", root / f".report.old-{dead}"
        for d in (out, stage, aside):
            d.mkdir(parents=True)
        (out / "notes.md").write_text("the user's")
        (out / OUTPUTS_INDEX).write_text(json.dumps(sorted(old)))
        (aside / SWAP_RECORD).write_text(json.dumps({"old": sorted(old), "new": sorted(new)}))
        for name, data in old.items():  # all old entries are aside before any new one moves in
            (aside / name).write_bytes(data)
        for k, (name, data) in enumerate(sorted(new.items())):
            (out if k < moved_in else stage).joinpath(name).write_bytes(data)
        assert recover_swaps(out) == [aside.name]
        assert {p.name: p.read_bytes() for p in out.iterdir() if p.name != OUTPUTS_INDEX} == {**old, "notes.md": b"the user's"}
        assert sorted(p.name for p in root.iterdir()) == ["report"]  # staging and the aside directory gone


def _results_table(path):
    """A made-up results table of two methods (what ``report`` redraws without evaluating)."""
    import pandas as pd

    from coin_app.evaluation.metrics import METRIC_KEYS
    from coin_app.evaluation.protocol import RESULT_COLUMNS

    rng = np.random.default_rng(0)
    rows = []
    for method in ("cig_td3", "itd3"):
        for seed in (0, 1):
            for test_seed in range(200000, 200004):
                row = dict.fromkeys(RESULT_COLUMNS, 0.0)
                row |= {"method": method, "variant": "default", "trained_seed": seed, "test_seed": test_seed}
                row |= {"scenario": "intersection", "agent_count": 4, "trained_agent_count": 4, "backend": "native"}
                row |= {k: float(rng.uniform(0, 1)) for k in METRIC_KEYS}
                row |= {"checkpoint": str(path.parent / f"{method}_{seed}" / "checkpoint"), "trained_env_steps": 1000}
                rows.append(row)
    pd.DataFrame(rows).to_csv(path, index=False)
    return path


@pytest.mark.parametrize("command", [["demo"], ["train"], ["evaluate", "p.npz"], ["sweep", "seeds"], ["config"]])
def test_repeated_set_groups_add_up(command):
    from coin_app.cli.parser import build_parser

    args = build_parser().parse_args([*command, "--set", "a=1", "b=2", "--set", "c=3"])
    assert args.set == ["a=1", "b=2", "c=3"]  # argparse's default for a repeated option kept only the last group
    assert build_parser().parse_args(command).set == []


def test_config_merges_every_set_group(capsys):
    assert main(["config", "--algo", "itd3", "--set", "tau=0.01", "--set", "warmup_steps=300", "horizon=60"]) == 0
    rows = {line.split()[0]: line.split()[1:] for line in capsys.readouterr().out.splitlines() if line.startswith("  ")}
    assert rows["tau"] == ["0.01", "--set"] and rows["warmup_steps"] == ["300", "--set"] and rows["horizon"] == ["60", "--set"]


def test_demo_checks_every_policys_layout_before_any_work(tmp_path, capsys):
    import torch

    def npz(name, inputs, outputs, meta):
        actor = torch.nn.Sequential(torch.nn.Linear(inputs, outputs), torch.nn.Tanh())
        return str(export_policy(actor, tmp_path / name, "numpy", meta=meta))

    native = npz("native.npz", 91, 2, {"scenario": "bottleneck", "env_config": {}})  # 91: the native observation
    narrow = npz("narrow.npz", 60, 2, {"scenario": "intersection"})  # no env_config: judged by its weights
    three = npz("three.npz", 91, 3, {"scenario": "intersection"})
    arena = npz("arena.npz", 91, 2, {"scenario": "arena"})
    out = tmp_path / "demo"
    cases = [
        (["--policy", native, "--set", "backend=metadrive"], "demo drives the native simulator, not backend 'metadrive'"),
        (["--policy", "heuristic", "--set", "backend=metadrive"], "allowed: backend native, or python -m coin_app evaluate POLICY"),
        (["--policy", native, "--set", "lidar_beams=36"], "this env gives 55 (bottleneck, native backend, 36 lidar beams)"),
        # the second policy is checked before the first drives (it used to fail after the first policy's whole episode)
        (["--policy", "heuristic", "--compare", narrow], f"{narrow} reads 60 observation numbers; this env gives 91 (intersection"),
        (["--policy", native, "--compare", three], f"{three} gives actions of shape (1, 3) for one vehicle; bottleneck takes (1, 2)"),
        (["--policy", "heuristic", "--compare", arena], f"{arena} is an arena policy; allowed: a driving policy"),
    ]
    for argv, phrase in cases:
        assert main(["demo", *argv, "--steps", "5", "--out", str(out)]) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1 and phrase in err, (argv, err)
        assert not out.exists()  # refused before any work
    # a scene it was not trained for runs, warned before the run and again under the figures
    assert main(["demo", "--policy", native, "--scenario", "intersection", "--steps", "2", "--no-gif", "--no-html", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    warnings = [
        f"warning: {native} was trained on bottleneck, not intersection: a scene it was not trained for",
        f"warning: {native} was trained with 20 vehicles, here 30: a count it was not trained for",  # the scenes' defaults
    ]
    assert captured.err.splitlines() == warnings and all(f"  {w}" in captured.out for w in warnings)
    # a CoPO actor reads the observation and its vehicle's LCF (92 numbers): driven with its per-vehicle draws, as evaluate
    # drives it (the check above counts the LCF; demo used to refuse it: "takes 92 observation numbers ... gives 91")
    copo = npz("copo.npz", 92, 2, {"scenario": "bottleneck", "env_config": {}, "lcf": {"mean": 0.2, "std": 0.1}})
    assert main(["demo", "--policy", copo, "--steps", "3", "--no-gif", "--no-html", "--out", str(tmp_path / "copo")]) == 0
    assert json.loads((tmp_path / "copo" / "metrics.json").read_text())[copo]["env_steps"] == 3


def test_evaluate_warns_on_a_scene_and_a_count_the_policy_was_not_trained_for(tmp_path, capsys):
    policy = export_policy(_tiny_actor(), tmp_path / "p.npz", "numpy", meta={"scenario": "bottleneck", "env_config": {"num_agents": 3}})
    out = tmp_path / "r.json"
    argv = ["evaluate", str(policy), "--scenario", "intersection", "--num-agents", "2", "--set", "horizon=5", "--seeds", "200000"]
    assert main([*argv, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    warnings = [
        f"warning: {policy} was trained on bottleneck, not intersection: a scene it was not trained for",
        f"warning: {policy} was trained with 3 vehicles, here 2: a count it was not trained for",
    ]
    assert captured.err.splitlines() == warnings  # before the run
    metrics_at = captured.out.index("success rate")
    assert all(captured.out.index(f"  {w}") > metrics_at for w in warnings)  # again under the figures
    assert json.loads(out.read_text())["warnings"] == warnings  # and with the results
    assert main(["evaluate", str(policy), "--num-agents", "3", "--set", "horizon=5", "--seeds", "200000"]) == 0
    assert "warning" not in capsys.readouterr().err  # its own scene and count: nothing to say
