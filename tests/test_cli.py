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
