"""The report's episode cache: an entry is found by the checkpoint's content and the grid, used only with the code that
wrote it, and gives back exactly the rows it was given."""

import json
import math
import shutil

from coin_app.algorithms.checkpoint_files import MANIFEST_FILE
from coin_app.evaluation.episode_cache import PACKAGE, EpisodeCache, checkpoint_identity, code_fingerprint
from coin_app.evaluation.protocol import EvalRun

SEEDS = [20000, 20001]


def _checkpoint(path, sha="ab" * 32):
    path.mkdir(parents=True)
    manifest = {"format": "coin_app.checkpoint", "files": {"actor.pt": {"size": 10, "sha256": sha}}}
    (path / MANIFEST_FILE).write_text(json.dumps(manifest))
    return path


def _rows(run):
    return [
        {"method": run.method, "test_seed": s, "success_rate": 1 / 3 + s, "episode_return": math.nan, "checkpoint": run.checkpoint}
        for s in SEEDS
    ]


def test_a_stored_entry_is_found_by_content_and_grid_with_the_same_code_only(tmp_path):
    run = EvalRun("cig_td3", "default", 1, str(_checkpoint(tmp_path / "a" / "checkpoint_000006")), 70000)
    cache = EpisodeCache(tmp_path / "cache", code="c1")
    assert cache.load(run, SEEDS, [10, 40], None, None) is None  # nothing stored yet
    rows = _rows(run)
    path = cache.store(run, SEEDS, [10, 40], None, None, rows)
    assert path.parent == tmp_path / "cache" and path.name.startswith("cig_td3-s1-checkpoint_000006-own-")
    assert "checkpoint" not in json.loads(path.read_text())["columns"]  # no machine's path in the entry
    back = cache.load(run, SEEDS, [40, 10], None, None)  # the counts' order does not matter
    assert back[0]["success_rate"] == rows[0]["success_rate"] and math.isnan(back[0]["episode_return"])
    assert [r["test_seed"] for r in back] == SEEDS and all(r["checkpoint"] == run.checkpoint for r in back)

    moved = tmp_path / "elsewhere" / "checkpoint_000006"  # the same files in another place: the same episodes
    shutil.copytree(run.checkpoint, moved)
    there = EvalRun(run.method, run.variant, run.trained_seed, str(moved), run.trained_env_steps)
    assert [r["checkpoint"] for r in cache.load(there, SEEDS, [10, 40], None, None)] == [str(moved)] * 2

    assert cache.load(run, SEEDS[:1], [10, 40], None, None) is None  # other seeds
    assert cache.load(run, SEEDS, [10], None, None) is None  # other counts
    assert cache.load(run, SEEDS, [10, 40], None, "metadrive") is None  # another simulator
    assert cache.load(EvalRun("itd3", "default", 1, run.checkpoint, 70000), SEEDS, [10, 40], None, None) is None
    other = tmp_path / "b" / "checkpoint_000006"  # another model's files under the same name
    assert cache.load(EvalRun("cig_td3", "default", 1, str(_checkpoint(other, "cd" * 32)), 70000), SEEDS, [10, 40], None, None) is None

    newer = EpisodeCache(tmp_path / "cache", code="c2")  # the simulator's or evaluator's code changed: evaluated again
    assert newer.load(run, SEEDS, [10, 40], None, None) is None
    newer.store(run, SEEDS, [10, 40], None, None, [{**r, "success_rate": 0.0} for r in rows])
    assert len(list((tmp_path / "cache").iterdir())) == 1  # the new entry replaced the old one
    assert [r["success_rate"] for r in newer.load(run, SEEDS, [10, 40], None, None)] == [0.0, 0.0]
    assert cache.load(run, SEEDS, [10, 40], None, None) is None


def test_a_checkpoint_without_a_manifest_or_a_torn_entry_is_never_read(tmp_path):
    bare = tmp_path / "bare"
    bare.mkdir()
    run = EvalRun("ippo", "default", 0, str(bare))
    cache = EpisodeCache(tmp_path / "cache", code="c1")
    assert checkpoint_identity(bare) is None and cache.store(run, SEEDS, None, None, None, _rows(run)) is None
    assert not (tmp_path / "cache").exists()
    good = EvalRun("ippo", "default", 0, str(_checkpoint(tmp_path / "ok")))
    path = cache.store(good, SEEDS, None, None, None, _rows(good))
    path.write_text(path.read_text()[:40])  # cut short (by hand: a store itself is atomic)
    assert cache.load(good, SEEDS, None, None, None) is None


def test_the_code_fingerprint_follows_the_simulator_maps_and_evaluator_not_the_report_or_the_learners(tmp_path):
    copy = tmp_path / "coin_app"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__", "shipped"))
    before = code_fingerprint(copy)
    assert before == code_fingerprint(PACKAGE) and len(before) == 16
    with open(copy / "evaluation" / "report.py", "a") as f:  # tables and figures: the episodes stay valid
        f.write("\n# a change to the report\n")
    for part in ("training/loop.py", "algorithms/gradient_step.py", "algorithms/td3/learner.py", "algorithms/cig_td3/losses.py"):
        with open(copy / part, "a") as f:  # how models learn: an evaluated model is keyed by its own content
            f.write("\n# a change to training\n")
    assert code_fingerprint(copy) == before
    for part in (
        "sim/dynamics.py",
        "sim/maps/intersection.json",
        "evaluation/metrics.py",
        "inference/__init__.py",
        "algorithms/td3/networks.py",
    ):
        text = (copy / part).read_text()
        (copy / part).write_text(text + "\n# changed\n")
        assert code_fingerprint(copy) != before, part
        (copy / part).write_text(text)
    assert code_fingerprint(copy) == before
