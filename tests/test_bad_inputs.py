"""Table-driven: every user-facing command given bad input ends in one clear line (exit 2), never a traceback, before any work."""

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
]


@pytest.fixture
def paths(tmp_path):
    """Paths the cases refer to: a missing one, a regular file, a truncated exported policy."""
    file = tmp_path / "plain.txt"
    file.write_text("not a directory")
    good = export_policy(_tiny_actor(), tmp_path / "good.npz", "numpy", meta={"scenario": "intersection"})
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    return {"missing": str(tmp_path / "missing"), "file": str(file), "truncated_npz": str(truncated), "good_npz": str(good)}


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
