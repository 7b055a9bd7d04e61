"""The command line: the demo writes its outputs; bad input exits 2 with a clear message."""

import json
import os
import subprocess
import sys
from pathlib import Path

from fixtures import tiny_cli
from PIL import Image

from coin_app.algorithms.checks import parse_overrides
from coin_app.cli import main
from coin_app.inference import export_policy, shipped_policies


def test_demo_writes_metrics_gif_and_plot(tmp_path, capsys):
    out = tmp_path / "demo"
    argv = ["demo", "--policy", "heuristic", "--scenario", "bottleneck", "--num-agents", "6", "--steps", "40", "--gif-every", "4"]
    assert main([*argv, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "success rate" in text and "avg travel steps" in text and str(out) in text
    metrics = json.loads((out / "metrics.json").read_text())["heuristic"]
    assert metrics["env_steps"] == 40 and metrics["num_vehicles"] >= 6
    counted = metrics["num_arrived"] + metrics["num_crashed"] + metrics["num_out_of_road"]
    assert metrics["efficiency"] == metrics["num_arrived"] - metrics["num_crashed"] - metrics["num_out_of_road"]
    assert counted <= metrics["num_vehicles"] + metrics["num_crashed"]
    with Image.open(out / "episode.gif") as gif:
        assert gif.n_frames == 11  # reset frame + every 4th of 40 steps
    with Image.open(out / "trajectories.png") as png:
        assert png.size[0] > 300


def test_demo_compares_two_policies_on_one_seed(tmp_path, capsys):
    # an exported policy file beside the heuristic driver: one GIF of two panels, one metric column each
    policy = export_policy(
        _still_actor(), tmp_path / "still.npz", "numpy", meta={"scenario": "bottleneck", "env_config": {"num_agents": 5}}
    )
    out = tmp_path / "demo"
    assert main(["demo", "--policy", str(policy), "--compare", "heuristic", "--steps", "20", "--gif-every", "10", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "bottleneck, 5 vehicles at reset" in text  # the policy's own scenario and vehicle count
    metrics = json.loads((out / "metrics.json").read_text())
    assert set(metrics) == {str(policy), "heuristic"}
    assert metrics["heuristic"]["num_vehicles"] >= 5 and metrics[str(policy)]["num_arrived"] == 0  # standing still arrives nowhere
    with Image.open(out / "episode.gif") as gif, Image.open(out / "trajectories.png"):
        assert gif.n_frames == 3 and gif.size[0] == 2 * gif.size[1]  # two 480 x 480 panels side by side


def _still_actor():
    """A torch actor whose every action is (0, -1): no steering, full brake."""
    import torch

    actor = torch.nn.Sequential(torch.nn.Linear(91, 2), torch.nn.Tanh())
    with torch.no_grad():
        actor[0].weight.zero_()
        actor[0].bias.copy_(torch.tensor([0.0, -20.0]))
    return actor


def test_policies_lists_every_shipped_policy(capsys):
    assert main(["policies"]) == 0
    text = capsys.readouterr().out
    assert all(f"{name}\n" in text for name in shipped_policies())


def test_parsing_and_refusals_import_neither_ray_nor_torch():
    # --help, a bad choice and a bad demo value are answered before any command's machinery is imported
    code = (
        "import sys\nfrom coin_app.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
        "codes = [main(['train', '--algo', 'sac']), main(['demo', '--steps', '0']), main(['sweep', 'seeds', '--scenario', 'x'])]\n"
        "print(codes, sorted(m for m in ('ray', 'torch') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[2, 2, 2] []"
    assert "invalid choice: 'sac'" in out.stderr and "bad --steps 0" in out.stderr and "invalid choice: 'x'" in out.stderr


def test_train_and_config_check_their_settings_before_importing_ray_or_torch(tmp_path):
    # the registry and the scenario configs are Ray-free: a bad --set, seed, scenario or budget costs no training machinery
    repo = Path(__file__).resolve().parent.parent
    cases = [
        (["train", "--set", "tau=2"], "error: bad value for 'tau': 2; allowed: a finite number in (0, 1]"),
        (
            ["train", "--set", "horizon=40", "--set", "horizon=50"],
            "error: --set gives horizon twice (40 and 50); allowed: one value per key",
        ),
        (["train", "--algo", "itd3", "--scenario", "arena"], "error: itd3 does not train on scenario 'arena'; allowed: intersection"),
        (["train", "--seed", "200003"], "error: bad seed 200003; allowed: an integer in [0, 90000)"),
        (["train", "--checkpoint-every", "0"], "error: bad checkpoint_every 0; allowed: an integer >= 1"),
        (["train", "--connect-timeout", "-1"], "error: bad --connect-timeout -1.0; allowed: a finite number of seconds > 0"),
        (["config", "--scale", "reduced", "--set", "tau=2"], "error: bad value for 'tau': 2; allowed: a finite number in (0, 1]"),
    ]
    code = (
        "import sys\nfrom coin_app.cli import main\n"
        f"codes = [main(a) for a in {[argv for argv, _ in cases]!r}]\n"
        "print(codes, sorted(m for m in ('ray', 'torch') if m in sys.modules))"
    )
    env = {**os.environ, "PYTHONPATH": str(repo)}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path, env=env)
    assert out.stdout.strip() == f"{[2] * len(cases)} []"  # no banner on stdout either: refused before it
    lines = out.stderr.splitlines()
    assert len(lines) == len(cases)  # one line each
    for line, (_, phrase) in zip(lines, cases):
        assert line.startswith(phrase), (line, phrase)
    assert list(tmp_path.iterdir()) == []  # nothing written (train's default --out is runs/...)


def test_bad_input_is_refused(capsys):
    assert main(["demo", "--set", "horizon=-5", "--steps", "1"]) == 2
    assert "horizon" in capsys.readouterr().err
    assert main(["demo", "--scenario", "highway", "--steps", "1"]) == 2
    assert "highway" in capsys.readouterr().err
    assert main(["demo", "--steps", "0"]) == 2
    assert "--steps" in capsys.readouterr().err


def test_parse_overrides_literals():
    assert parse_overrides(["crash_penalty=10", "allow_respawn=False", "dynamics={'dt': 0.05}"]) == {
        "crash_penalty": 10,
        "allow_respawn": False,
        "dynamics": {"dt": 0.05},
    }


TINY_TRAIN = [*tiny_cli("itd3", "bottleneck"), "--checkpoint-every", "1"]


def test_train_evaluate_and_resume(no_ray, tmp_path, capsys):
    import resource

    import ray

    out = tmp_path / "run"

    def own_cpu():  # this process's CPU seconds, read without the code under test
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    try:
        start = own_cpu()
        assert main(["train", "--algo", "itd3", "--steps", "150", "--out", str(out), *TINY_TRAIN]) == 0
        first_own = own_cpu() - start
        ckpt = out / "checkpoint"
        text = capsys.readouterr().out
        assert "iter" in text and str(ckpt) in text and (ckpt / "coin_app.json").exists()
        assert " h" in text.split("cpu ")[1]  # each iteration's line shows the run's CPU time
        # the run's CPU time counts this process (and its Ray session's) from the start of train(): at least what it used here
        first = json.loads((out / "summary.json").read_text())
        saved = json.loads((ckpt / "coin_app.json").read_text())
        assert first_own - 0.1 <= first["run_cpu_s"] and 0 < saved["cpu_s"] <= first["run_cpu_s"]
        assert 0 < saved["wall_s"] <= first["run_wall_s"]
        assert main(["evaluate", str(ckpt), "--episodes", "2", "--out", str(tmp_path / "eval.json")]) == 0
        text = capsys.readouterr().out
        assert "success rate" in text and "(" in text and json.loads((tmp_path / "eval.json").read_text())["seeds"] == [200000, 200001]
        steps = first["env_steps"]
        start = own_cpu()
        assert main(["train", "--algo", "itd3", "--steps", str(steps + 100), "--out", str(out), "--resume", str(ckpt), *TINY_TRAIN]) == 0
        second_own = own_cpu() - start
        text = capsys.readouterr().out
        assert "resumed from" in text
        second = json.loads((out / "summary.json").read_text())
        assert second["env_steps"] >= steps + 100
        # a resumed run's clocks go on from its checkpoint's
        assert second["run_cpu_s"] >= saved["cpu_s"] + second_own - 0.1 and second["run_wall_s"] > saved["wall_s"] + second["wall_s"] - 0.1
        # a CPU budget counts the whole run: one already spent stops a resume before its first iteration, with a checkpoint
        spent = json.loads((ckpt / "coin_app.json").read_text())["cpu_s"] / 3600  # where the resumed clock starts
        argv = ["train", "--algo", "itd3", "--steps", "1000000", "--out", str(out), "--resume", str(ckpt), "--max-cpu-hours"]
        assert main([*argv, f"{spent:.9f}", *TINY_TRAIN]) == 0
        third = json.loads((out / "summary.json").read_text())
        assert (third["stopped"], third["env_steps"]) == ("max_cpu_hours", second["env_steps"]) and third["run_cpu_s"] >= spent * 3600
        assert "stopped early (max_cpu_hours)" in capsys.readouterr().out
        # ten more CPU seconds (more than a resume's start-up): it trains until the run has used them, then stops between
        # iterations
        start_cpu = json.loads((ckpt / "coin_app.json").read_text())["cpu_s"]
        assert main([*argv, f"{(start_cpu + 10) / 3600:.9f}", *TINY_TRAIN]) == 0
        fourth = json.loads((out / "summary.json").read_text())
        assert fourth["stopped"] == "max_cpu_hours" and fourth["run_cpu_s"] >= start_cpu + 10 - 1e-3
        assert third["env_steps"] < fourth["env_steps"] < 1_000_000
    finally:
        ray.shutdown()


def test_train_and_evaluate_refuse_bad_input(tmp_path, capsys):
    assert main(["train", "--algo", "sac", "--steps", "10", "--out", str(tmp_path / "x")]) == 2
    assert "invalid choice: 'sac'" in capsys.readouterr().err
    assert main(["train", "--steps", "10", "--set", "colour=3", "--out", str(tmp_path / "x")]) == 2
    assert "colour" in capsys.readouterr().err
    assert main(["train", "--steps", "10", "--set", "policy_delay=0", "--out", str(tmp_path / "x")]) == 2
    assert "bad value for 'policy_delay': 0; allowed: an integer >= 1" in capsys.readouterr().err
    # training seeds stay below the validation (100000 + k) and test (200000 + k) seeds
    assert main(["train", "--steps", "10", "--seed", "200003", "--out", str(tmp_path / "x")]) == 2
    assert "bad seed 200003; allowed: an integer in [0, 90000)" in capsys.readouterr().err
    assert main(["train", "--steps", "10", "--max-cpu-hours", "0", "--out", str(tmp_path / "x")]) == 2
    assert "bad max_cpu_hours 0.0; allowed: a number > 0 or None" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "missing"), "--episodes", "2"]) == 2
    assert "missing" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # refused before any work started


def test_config_prints_a_reduced_trials_merged_settings_with_their_origins(capsys):
    from tuning import get_experiment
    from tuning.experiment import expand_grid, trial_overrides

    assert main(["config", "--algo", "cig_td3", "--scale", "reduced", "--set", "tau=0.01"]) == 0
    rows = {}
    for line in capsys.readouterr().out.splitlines():
        parts = line.split(maxsplit=2)
        if line.startswith("  ") and len(parts) == 3:
            rows[parts[0]] = (parts[1], parts[2])
    # the trial the sweep itself would run (seed 0 of sweep seeds --scale reduced), merged by the sweep's own code
    space = get_experiment("seeds").param_space("intersection", "reduced", ("cig_td3",), (0,), overrides={"tau": 0.01})
    trial = trial_overrides(expand_grid(space)[0])
    for key, value in trial.items():
        assert rows[key][0] == repr(value), key
    assert rows["tau"] == ("0.01", "--set")
    assert rows["policy_delay"] == ("1", "preset 'reduced' (coin_app.algorithms.cig_td3.settings)")
    assert rows["num_agents"] == ("4", "quick scenario (registry.quick_scenario('intersection'))")
    assert rows["lr_decay_start"][0] == "20000" and rows["lr_decay_start"][1].startswith("reduced scale: decay")
    assert rows["target_noise"] == ("0.1", "default") and rows["crash_penalty"] == ("5.0", "ScenarioConfig default")
    assert main(["config", "--algo", "cig_td3", "--set", "preset=metadrive_compat"]) == 0
    assert "crash_penalty                  10.0                     preset 'metadrive_compat'" in capsys.readouterr().out
    assert main(["config", "--set", "tau=2"]) == 2
    assert "bad value for 'tau': 2" in capsys.readouterr().err
