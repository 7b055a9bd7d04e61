"""The command line: the demo writes its outputs; bad input exits 2 with a clear message."""

import json

from PIL import Image

from coin_app.cli import main, parse_overrides


def test_demo_writes_metrics_gif_and_plot(tmp_path, capsys):
    out = tmp_path / "demo"
    code = main(["demo", "--scenario", "bottleneck", "--num-agents", "6", "--steps", "40", "--gif-every", "4", "--out", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "success rate" in text and "avg travel steps" in text and str(out) in text
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["env_steps"] == 40 and metrics["num_vehicles"] >= 6
    counted = metrics["num_arrived"] + metrics["num_crashed"] + metrics["num_out_of_road"]
    assert metrics["efficiency"] == metrics["num_arrived"] - metrics["num_crashed"] - metrics["num_out_of_road"]
    assert counted <= metrics["num_vehicles"] + metrics["num_crashed"]
    with Image.open(out / "episode.gif") as gif:
        assert gif.n_frames == 11  # reset frame + every 4th of 40 steps
    with Image.open(out / "trajectories.png") as png:
        assert png.size[0] > 300


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


TINY_TRAIN = ["--scenario", "bottleneck", "--num-agents", "3", "--set", "horizon=40", "max_agent_steps=40", "warmup_steps=60"]
TINY_TRAIN += ["train_batch_size_per_learner=16", "hidden=16", "eval_every=0", "--checkpoint-every", "1"]


def test_train_evaluate_and_resume(tmp_path, capsys):
    import ray

    out = tmp_path / "run"
    try:
        assert main(["train", "--algo", "itd3", "--steps", "150", "--out", str(out), *TINY_TRAIN]) == 0
        ckpt = out / "checkpoint"
        text = capsys.readouterr().out
        assert "iter" in text and str(ckpt) in text and (ckpt / "coin_app.json").exists()
        assert main(["evaluate", str(ckpt), "--episodes", "2", "--out", str(tmp_path / "eval.json")]) == 0
        text = capsys.readouterr().out
        assert "success rate" in text and "(" in text and json.loads((tmp_path / "eval.json").read_text())["seeds"] == [200000, 200001]
        first = json.loads((out / "summary.json").read_text())["env_steps"]
        assert main(["train", "--algo", "itd3", "--steps", str(first + 100), "--out", str(out), "--resume", str(ckpt), *TINY_TRAIN]) == 0
        text = capsys.readouterr().out
        assert "resumed from" in text
        assert json.loads((out / "summary.json").read_text())["env_steps"] >= first + 100
    finally:
        ray.shutdown()


def test_train_and_evaluate_refuse_bad_input(tmp_path, capsys):
    assert main(["train", "--algo", "sac", "--steps", "10", "--out", str(tmp_path / "x")]) == 2
    assert "unknown algorithm 'sac'" in capsys.readouterr().err
    assert main(["train", "--steps", "10", "--set", "colour=3", "--out", str(tmp_path / "x")]) == 2
    assert "colour" in capsys.readouterr().err
    assert main(["train", "--steps", "10", "--set", "policy_delay=0", "--out", str(tmp_path / "x")]) == 2
    assert "bad value for 'policy_delay': 0; allowed: an integer >= 1" in capsys.readouterr().err
    # training seeds stay below the validation (100000 + k) and test (200000 + k) seeds
    assert main(["train", "--steps", "10", "--seed", "200003", "--out", str(tmp_path / "x")]) == 2
    assert "bad seed 200003; allowed: an integer in [0, 90000)" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "missing"), "--episodes", "2"]) == 2
    assert "missing" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # refused before any work started
