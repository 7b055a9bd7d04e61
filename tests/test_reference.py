"""The COIN authors' actors as a reference: the torch-free reader, the finder, the protocol's plan, the table, resuming."""

import itertools
import math
import os
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from coin_app.cli import main
from coin_app.evaluation import reference
from coin_app.evaluation.episode_cache import EpisodeCache
from coin_app.inference.coin_actors import ACTORS_ENV, find_coin_actors, load_coin_actor, read_state_dict


def _official_actor(obs_dim: int, seed: int = 0):
    """A torch module shaped as the official ``models/coin.py`` Actor (attribute ``l1``: Linear/ReLU x3, Linear), and its forward."""
    import torch

    torch.manual_seed(seed)

    class Actor(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.l1 = torch.nn.Sequential(
                torch.nn.Linear(obs_dim, 16),
                torch.nn.ReLU(),
                torch.nn.Linear(16, 16),
                torch.nn.ReLU(),
                torch.nn.Linear(16, 16),
                torch.nn.ReLU(),
                torch.nn.Linear(16, 2),
            )

        def forward(self, x):
            return torch.tanh(self.l1(x))  # max_action 1

    return Actor()


def _save(actor, path):
    import torch

    torch.save(actor.state_dict(), path)
    return path


def test_reader_gives_torch_tensors_bit_for_bit_and_the_actor_its_forward(tmp_path):
    import torch

    actor = _official_actor(96)
    path = _save(actor, tmp_path / "TD3_bottleneck_3000_best_model_325_1.00_actor")
    state = read_state_dict(path)
    assert list(state) == list(actor.state_dict())
    for key, tensor in actor.state_dict().items():
        assert state[key].dtype == np.float32 and np.array_equal(state[key], tensor.numpy()), key
    policy = load_coin_actor(path)
    x = np.random.default_rng(0).normal(size=(5, 96)).astype(np.float32)
    with torch.no_grad():
        expected = actor(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(policy(x), expected, atol=1e-6)
    assert policy.obs_dim == 96
    assert policy.meta | {"source": None} == {
        "source": None,
        "file": path.name,
        "scene": "bottleneck",
        "seed": 3000,
        "episode": 325,
        "train_success": "1.00",
    }


def test_reader_reads_a_transposed_view_by_its_strides(tmp_path):
    import torch

    w = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    torch.save({"w": w.t(), "b": w[1]}, tmp_path / "sd")  # a non-contiguous view and an offset into the same storage
    state = read_state_dict(tmp_path / "sd")
    assert np.array_equal(state["w"], np.arange(12, dtype=np.float32).reshape(3, 4).T)
    assert np.array_equal(state["b"], np.array([4, 5, 6, 7], np.float32))


def test_reader_refuses_anything_but_a_state_dict_of_tensors(tmp_path):
    import torch

    torch.save(torch.nn.Linear(3, 2), tmp_path / "module")  # a whole module: its pickle names torch.nn classes
    with pytest.raises(pickle.UnpicklingError, match="allowed: a state_dict of float tensors"):
        read_state_dict(tmp_path / "module")
    (tmp_path / "plain").write_text("not a zip")
    with pytest.raises(ValueError, match="not a torch state_dict file"):
        read_state_dict(tmp_path / "plain")
    with zipfile.ZipFile(tmp_path / "empty.zip", "w") as z:
        z.writestr("x/other", b"")
    with pytest.raises(ValueError, match="no data.pkl"):
        read_state_dict(tmp_path / "empty.zip")
    torch.save({"l1.0.weight": torch.zeros(2, 2)}, tmp_path / "partial")
    with pytest.raises(ValueError, match="lacks l1.0.bias"):
        load_coin_actor(tmp_path / "partial")


def test_finder_takes_both_layouts_and_the_best_file_per_seed(tmp_path):
    flat = tmp_path / "copy" / "roundabout"
    flat.mkdir(parents=True)
    for name in ("TD3_roundabout_1000_best_model_165_0.90_actor", "TD3_roundabout_2000_best_model_255_0.95_actor", "notes.txt"):
        (flat / name).write_bytes(b"")
    clone = tmp_path / "clone" / "runs" / "roundabout" / "1000" / "model"
    clone.mkdir(parents=True)
    for name in (
        "TD3_roundabout_1000_best_model_120_0.86_actor",
        "TD3_roundabout_1000_best_model_165_0.90_actor",
        "TD3_roundabout_1000_best_model_140_0.90_actor",  # same success, earlier episode
        "TD3_roundabout_1000_best_model_165_0.90_local_critic",
    ):
        (clone / name).write_bytes(b"")
    assert find_coin_actors(tmp_path / "copy", "roundabout") == {
        1000: flat / "TD3_roundabout_1000_best_model_165_0.90_actor",
        2000: flat / "TD3_roundabout_2000_best_model_255_0.95_actor",
    }
    assert find_coin_actors(tmp_path / "clone", "roundabout") == {1000: clone / "TD3_roundabout_1000_best_model_165_0.90_actor"}
    assert find_coin_actors(tmp_path / "copy", "bottleneck") == {}


def test_protocol_seeds_config_and_plan(tmp_path):
    assert reference.episode_seeds(5) == [1000, 1100, 1200, 1300, 1400]
    config = reference.reference_config("bottleneck", "native")
    assert (config.num_agents, config.obs_dim, config.crash_penalty, config.lidar_range) == (20, 96, 10.0, 40.0)
    assert config.solid_center_line
    config = reference.reference_config("roundabout", "native")
    assert (config.num_agents, config.obs_dim) == (40, 91)
    scene = tmp_path / "intersection"
    scene.mkdir()
    for seed in (1000, 2000):
        (scene / f"TD3_intersection_{seed}_best_model_150_0.90_actor").write_bytes(b"")
    tasks = reference.plan(tmp_path, ["intersection"], ["native"], None, 3)
    assert [(t.train_seed, t.episode_seeds) for t in tasks] == [(1000, (1000, 1100, 1200)), (2000, (1000, 1100, 1200))]
    with pytest.raises(ValueError, match=r"training seed\(s\) \[3000\].*allowed: 1000, 2000"):
        reference.plan(tmp_path, ["intersection"], ["native"], [3000], 3)
    with pytest.raises(ValueError, match="no roundabout actors"):
        reference.plan(tmp_path, ["roundabout"], ["native"], None, 3)
    with pytest.raises(ValueError, match="bad --episodes 0"):
        reference.plan(tmp_path, ["intersection"], ["native"], None, 0)


def _rows(scene, backend, per_seed):
    """Result rows: ``per_seed`` maps a training seed to its episodes' (arrived, crashed, off-road, timed-out) counts."""
    rows = []
    for seed, episodes in per_seed.items():
        for k, (a, c, o, t) in enumerate(episodes):
            n = a + c + o + t
            rows.append(
                {"scene": scene, "backend": backend, "train_seed": seed, "episode_seed": 1000 + 100 * k, "success_rate": a / n}
                | {"collision_rate": c / n, "out_of_road_rate": o / n, "timeout_rate": t / n, "num_timeout": t, "wall_s": 30.0}
            )
    return pd.DataFrame(rows)


def test_summary_is_the_mean_over_seeds_of_episode_means_with_their_spread():
    # seed 1000: episodes at 80 % and 60 % success (mean 70); seed 2000: 90 % and 100 % (mean 95)
    results = _rows("intersection", "native", {1000: [(8, 2, 0, 0), (6, 2, 1, 1)], 2000: [(9, 0, 1, 0), (10, 0, 0, 0)]})
    table = reference.summary_table(results)
    row = table.iloc[0]
    assert (row.scene, row.backend, row.seeds, row.episodes, row.vehicles) == ("intersection", "native", 2, 4, 30)
    assert row.success_rate_mean == pytest.approx(82.5)
    assert row.success_rate_sd == pytest.approx(math.sqrt(2 * 12.5**2))  # sample sd of 70 and 95
    assert (row.success_rate_min, row.success_rate_max) == pytest.approx((70.0, 95.0))
    assert row.collision_rate_mean == pytest.approx((20 + 20 + 0 + 0) / 4)
    assert row.timeout_rate_mean == pytest.approx(2.5) and row.timeouts_per_episode == pytest.approx(0.25)
    text = reference.to_markdown(table)
    assert "| intersection (30) | native | 82.5 ± 17.7 (70.0–95.0) | 10.0 | 5.0 | 2.5 | 2 × 2 | 2 | 88.78 |" in text


def test_gaps_are_paired_by_seed_and_episode_with_their_standard_error_over_seeds():
    # native: seed 1000 at 80 and 60 %, seed 2000 at 90 and 100 %, and an episode MetaDrive did not run (left out)
    native = _rows("intersection", "native", {1000: [(8, 2, 0, 0), (6, 2, 1, 1)], 2000: [(9, 0, 1, 0), (10, 0, 0, 0), (0, 0, 0, 1)]})
    # MetaDrive: seed 1000 at 90 and 70 % (differences -10, -10), seed 2000 at 80 and 100 % (+10, 0), seed 3000 alone
    metadrive = _rows(
        "intersection", "metadrive", {1000: [(9, 1, 0, 0), (7, 2, 0, 1)], 2000: [(8, 1, 0, 1), (10, 0, 0, 0)], 3000: [(1, 0, 0, 0)]}
    )
    gaps = reference.gap_table(pd.concat([native, metadrive]))
    row = gaps.iloc[0]
    assert (row.scene, row.seeds, row.episodes) == ("intersection", 2, 4)
    assert row.success_rate_gap == pytest.approx((-10 + 5) / 2)  # seed means -10 and +5
    assert row.success_rate_se == pytest.approx(math.sqrt(2 * 7.5**2) / math.sqrt(2))
    assert row.timeout_rate_gap == pytest.approx(((0 + 0) / 2 + (-10 + 0) / 2) / 2)  # seed means 0 and -5
    text = reference.gap_markdown(gaps)
    assert "| intersection (30) | 4 (2 seeds) | -2.5 (7.5) | -2.5 (2.5) | no |" in text
    assert reference.gap_table(native).empty


def test_run_resumes_and_keeps_every_finished_episode(tmp_path, monkeypatch):
    ran = []

    def fake(task):
        ran.append((task.backend, task.train_seed, task.episode_seeds))
        return [
            {"scene": task.scene, "backend": task.backend, "train_seed": task.train_seed, "episode_seed": s, "success_rate": 1.0}
            | {"collision_rate": 0.0, "out_of_road_rate": 0.0, "timeout_rate": 0.0, "num_timeout": 0, "actor": task.actor.name}
            for s in task.episode_seeds
        ]

    monkeypatch.setattr(reference, "run_task", fake)
    actor = tmp_path / "TD3_intersection_1000_best_model_150_0.90_actor"
    tasks = [reference.Task("intersection", "native", 1000, actor, (1000, 1100))]
    tasks += [reference.Task("intersection", "metadrive", 1000, actor, (s,)) for s in (1000, 1100)]
    out = tmp_path / "out"
    reference.run_reference(tasks[:2], out, settings={"command": "python -m coin_app evaluate-reference"})
    assert len(ran) == 2 and len(reference.load_results(out)) == 3
    assert "| intersection (30) | MetaDrive 0.4.3 | 100.0 | 0.0 | 0.0 | 0.0 | 1 × 1 |" in (out / "table.md").read_text()
    reference.run_reference(tasks, out)  # only the missing MetaDrive episode runs
    assert ran[2:] == [("metadrive", 1000, (1100,))]
    results = reference.load_results(out)
    assert len(results) == 4 and not results.duplicated(reference.KEY).any()


def test_command_refuses_a_missing_actors_directory_in_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv(ACTORS_ENV, raising=False)
    assert main(["evaluate-reference", "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"pass --actors DIR or set {ACTORS_ENV}" in err
    assert main(["evaluate-reference", "--actors", str(tmp_path / "nope"), "--out", str(tmp_path / "out")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["evaluate-reference", "--actors", str(tmp_path), "--backends", "native", "--out", str(tmp_path / "out")]) == 2
    assert "no intersection actors" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_readme_shows_the_committed_reference_table():
    committed = Path(__file__).resolve().parents[1] / "docs" / "results" / "reference" / reference.TABLE_MD
    if not committed.is_file():
        pytest.skip("no committed reference table")
    lines = committed.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| scene (vehicles) | simulator |"))
    rows = [line for line in itertools.takewhile(lambda line: line.startswith("|"), lines[start:])]
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text().splitlines()
    assert len(rows) > 2 and all(row in readme for row in rows)


def test_tables_are_written_whole_or_not_at_all(tmp_path, monkeypatch):
    """A disk that fills while the tables are rewritten leaves the previous tables as they were (no torn file)."""
    row = {"scene": "intersection", "backend": "native", "train_seed": 1000, "episode_seed": 1000, "success_rate": 1.0}
    row |= {"collision_rate": 0.0, "out_of_road_rate": 0.0, "timeout_rate": 0.0, "num_timeout": 0, "actor": "a"}
    reference.write_tables(pd.DataFrame([row]), tmp_path, {"command": "first"})
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full)
    with pytest.raises(OSError, match="No space left"):
        reference.write_tables(pd.DataFrame([row | {"success_rate": 0.0}]), tmp_path, {"command": "second"})
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no partial file left, nothing changed


def test_the_authors_rows_on_a_reports_test_seeds_are_their_episodes_in_the_results_layout(tmp_path, monkeypatch):
    from coin_app.evaluation.evaluate import evaluate_policy
    from coin_app.evaluation.protocol import RESULT_COLUMNS
    from coin_app.sim.config import make_config

    small = make_config("intersection", "metadrive_compat", num_agents=3, horizon=40, max_agent_steps=40)
    monkeypatch.setattr(reference, "reference_config", lambda scene, backend: small)
    (tmp_path / "intersection").mkdir()
    for seed in (1000, 2000):
        _save(_official_actor(91, seed), tmp_path / "intersection" / f"TD3_intersection_{seed}_best_model_150_0.90_actor")
    rows = reference.test_seed_rows(tmp_path, "intersection", [200000, 200001])
    assert list(rows.columns) == list(RESULT_COLUMNS)
    assert rows[["trained_seed", "test_seed"]].values.tolist() == [[1000, 200000], [1000, 200001], [2000, 200000], [2000, 200001]]
    assert set(rows["method"]) == {reference.REFERENCE_METHOD} and set(rows["agent_count"]) == {3}
    for seed in (1000, 2000):
        path = tmp_path / "intersection" / f"TD3_intersection_{seed}_best_model_150_0.90_actor"
        want = evaluate_policy(load_coin_actor(path), small, [200000, 200001])
        got = rows[rows["trained_seed"] == seed]
        assert got["success_rate"].tolist() == [w["success_rate"] for w in want]
        assert got["episode_length"].tolist() == [w["env_steps"] for w in want]
        assert set(got["checkpoint"]) == {str(path)}
    with pytest.raises(ValueError, match="no roundabout actors"):
        reference.test_seed_rows(tmp_path, "roundabout", [200000])
    # with a cache: the same rows, and read back the second time without an episode driven
    cache = EpisodeCache(tmp_path / "episodes")
    first = reference.test_seed_rows(tmp_path, "intersection", [200000, 200001], cache=cache)
    pd.testing.assert_frame_equal(first.drop(columns="wall_time_s"), rows.drop(columns="wall_time_s"))
    monkeypatch.setattr(reference, "_episodes_of", lambda task: pytest.fail(f"{task} driven again"))
    pd.testing.assert_frame_equal(reference.test_seed_rows(tmp_path, "intersection", [200000, 200001], cache=cache), first)
