"""Evaluation protocol and report on one real smoke sweep: generalization table, deterministic parallel
evaluation, broken checkpoints reported by name, and every report output produced."""

import html
import json
import shutil

import numpy as np
import pandas as pd
import pytest

from coin_app.algorithms.checkpoint_files import verify
from coin_app.algorithms.checkpoints import load_module
from coin_app.cli import main
from coin_app.evaluation import protocol
from coin_app.evaluation.archive import BOOKKEEPING
from coin_app.evaluation.episode_cache import EpisodeCache
from coin_app.evaluation.plots import curve_axes, mean_curve, plot_learning_curves
from coin_app.evaluation.protocol import RESULT_COLUMNS, EvalRun, run_evaluation
from coin_app.evaluation.report import learning_curves, training_cost, write_cost
from coin_app.evaluation.sweep_results import load_trials
from coin_app.sim.seeds import TEST_SEED_BASE, VALIDATION_SEED_BASE, validation_seeds

METRIC_COLUMNS = [c for c in RESULT_COLUMNS if c != "wall_time_s"]


@pytest.fixture(scope="module")
def sweep_dir(ray_session, tmp_path_factory):
    """A finished smoke generalization sweep of CIG-TD3 and IPPO (seed 0, 1000 env steps, counts 2 and 4)."""
    storage = tmp_path_factory.mktemp("sweeps")
    assert main(["sweep", "generalization", "--smoke", "--algos", "cig_td3", "ippo", "--storage", str(storage)]) == 0
    return storage / "generalization-intersection-smoke"


def _runs(sweep_dir):
    return [EvalRun(t.config["algo"], t.config["variant"], t.config["seed"], str(t.final_checkpoint)) for t in load_trials(sweep_dir)]


def test_generalization_table_from_a_finished_sweep(sweep_dir, capsys):
    table = pd.read_csv(sweep_dir / "generalization.csv")
    assert list(table.columns) == [
        "method",
        "variant",
        "seed",
        "scenario",
        "agent_count",
        "trained_agent_count",
        "metric",
        "value",
        "std",
        "episodes",
    ]
    assert len(table) == 2 * 2 * 7 and set(table["agent_count"]) == {2, 4} and set(table["trained_agent_count"]) == {4}
    assert set(table["method"]) == {"cig_td3", "ippo"}
    success = table[table.metric == "success_rate"]
    assert success["value"].between(0, 1).all() and (table["episodes"] == 2).all()
    # the standalone command re-evaluates the same checkpoints: deterministic, so the same table
    assert main(["generalize", str(sweep_dir), "--counts", "2", "4", "--test-seeds", "2"]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(sweep_dir / "generalization.csv"), table)
    assert main(["generalize", str(sweep_dir.parent)]) == 2
    assert "is not a coin_app sweep directory" in capsys.readouterr().err


def test_evaluation_is_deterministic_in_process_and_in_workers(sweep_dir):
    runs = _runs(sweep_dir)
    seeds = [TEST_SEED_BASE + k for k in range(3)]
    first = run_evaluation(runs, seeds, counts=[2], workers=1, log=lambda _: None)
    spread = run_evaluation(runs, seeds, counts=[2], workers=2, log=lambda _: None)
    assert not first.failures and len(first.table) == len(runs) * 2 * 3  # (training count 4 and 2) x 3 seeds
    assert set(first.table["test_seed"]) == set(seeds) and first.table["test_seed"].min() >= TEST_SEED_BASE > VALIDATION_SEED_BASE
    assert (first.table["episode_length"] > 0).all() and (first.table["wall_time_s"] > 0).all()
    pd.testing.assert_frame_equal(first.table[METRIC_COLUMNS], spread.table[METRIC_COLUMNS])


def test_an_evaluation_stopped_and_run_again_with_its_cache_evaluates_only_the_runs_it_had_not(sweep_dir, tmp_path, monkeypatch):
    runs = _runs(sweep_dir)
    seeds = [TEST_SEED_BASE + k for k in range(2)]
    fresh = run_evaluation(runs, seeds, counts=[2], log=lambda _: None)
    cache = EpisodeCache(tmp_path / "episodes")
    run_evaluation(runs[:1], seeds, counts=[2], cache=cache, log=lambda _: None)  # stopped after its first model
    evaluated, real = [], protocol._task
    monkeypatch.setattr(protocol, "_task", lambda run, *rest: (evaluated.append(run.method), real(run, *rest))[1])
    lines = []
    again = run_evaluation(runs, seeds, counts=[2], cache=cache, log=lines.append)
    assert evaluated == [runs[1].method] and any("1 of the 2 runs' episodes read from" in line for line in lines)
    pd.testing.assert_frame_equal(again.table[METRIC_COLUMNS], fresh.table[METRIC_COLUMNS])
    evaluated.clear()
    third = run_evaluation(runs, seeds, counts=[2], cache=cache, log=lambda _: None)
    assert evaluated == [] and len(list((tmp_path / "episodes").iterdir())) == 2
    pd.testing.assert_frame_equal(third.table, again.table)  # wall times included: read back as stored


def test_missing_or_corrupt_checkpoint_is_reported_by_name_and_the_rest_still_runs(sweep_dir, tmp_path):
    good = _runs(sweep_dir)[0]
    corrupt = tmp_path / "corrupt_ckpt"
    shutil.copytree(good.checkpoint, corrupt)
    for f in (corrupt / "learner_group").rglob("*"):
        if f.is_file():
            f.write_bytes(b"not a checkpoint")
    missing = EvalRun("itd3", "default", 3, str(tmp_path / "missing_ckpt"))
    broken = EvalRun("cig_td3", "default", 7, str(corrupt))
    lines = []
    ev = run_evaluation([missing, good, broken], [TEST_SEED_BASE], workers=2, log=lines.append)
    assert sorted(f["checkpoint"] for f in ev.failures) == sorted([missing.checkpoint, broken.checkpoint])
    assert set(ev.table["checkpoint"]) == {good.checkpoint} and len(ev.table) == 1
    assert any("FAILED itd3 seed 3" in line and "missing_ckpt" in line for line in lines)
    assert any("FAILED cig_td3 seed 7" in line and "corrupt_ckpt" in line for line in lines)


def test_report_from_a_real_sweep_writes_every_output(sweep_dir, tmp_path, capsys):
    out = tmp_path / "report"
    argv = ["report", str(sweep_dir), "--out", str(out), "--test-seeds", "2", "--tsne-samples", "40", "--tsne-episodes", "1"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "report summary:" in printed and "figures: 9 of 9 drawn" in printed
    assert "attention: " in printed and "mean share within 15 m" in printed
    expected = [
        "results.csv",
        "evaluation.json",
        "table_main.md",
        "table_main.csv",
        "table_main.tex",
        "stats.csv",
        "marl_eval.json",
        "table_cost.md",  # the trials recorded their clocks
        "table_cost.csv",
        "radar_intersection.png",
        "generalization_intersection.png",
        "learning_curves_intersection.png",
        "learning_curves_cpu_s_intersection.png",  # the trials recorded their CPU and wall clocks
        "learning_curves_wall_s_intersection.png",
        "trajectories_intersection_cig_td3.png",
        "trajectories_intersection_ippo.png",
        "latent_tsne.png",
        "attention_intersection.png",
        "attention_intersection.csv",
        "report.html",
    ]
    for name in expected:
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    for png in out.glob("*.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000, png.name
    results = pd.read_csv(out / "results.csv")
    # 2 models x counts {2, 4} x 2 test seeds, one row per episode
    assert len(results) == 8 and set(results["agent_count"]) == {2, 4}
    stats = pd.read_csv(out / "stats.csv")
    assert list(stats["unit"]) == ["episode"] * 3 + ["seed"] * 3 and (stats["baseline"] == "ippo").all()
    assert list(stats["metric"]) == ["success_rate", "safety", "efficiency"] * 2
    episodes, seeds = stats[stats["unit"] == "episode"], stats[stats["unit"] == "seed"]
    assert (episodes["n_pairs"] == 2).all() and np.allclose(stats["threshold"], 0.01 / 3)
    assert (seeds["n_pairs"] == 1).all() and seeds["p"].isna().all()  # one trained seed per method: no seed-level test
    md = (out / "table_main.md").read_text()
    assert "| cig_td3 |" in md and "| ippo |" in md and "**" in md
    page = html.unescape((out / "report.html").read_text())
    assert page.count("data:image/png;base64,") == 9 and "python -m coin_app report" in page and '"experiment": "generalization"' in page
    assert "<td>torch</td>" in page and '"algo": "ippo"' in page  # versions and each model's metadata
    marl = json.loads((out / "marl_eval.json").read_text())
    assert set(marl["coin_app"]) == {"intersection", "intersection_2agents"}
    # the same report again reads every episode from its cache (OUT/episodes): the same results, nothing evaluated
    assert len(list((out / "episodes").glob("*.json"))) == 2
    assert main(argv) == 0
    assert "2 of the 2 runs' episodes read from" in capsys.readouterr().out
    pd.testing.assert_frame_equal(pd.read_csv(out / "results.csv"), results)
    # re-plotting from the results file alone evaluates nothing and gives the same main table
    again = tmp_path / "again"
    assert main(["report", str(out / "results.csv"), "--out", str(again), "--tsne-samples", "40", "--tsne-episodes", "1"]) == 0
    assert (again / "table_main.md").read_text() == md
    assert main(["report", str(tmp_path / "nowhere"), "--out", str(again)]) == 2
    assert "is not a results file, a sweep directory" in capsys.readouterr().err


def test_report_refuses_bad_options_before_any_work(tmp_path, capsys):
    for flag, value, message in [
        ("--workers", "0", "bad --workers 0"),
        ("--alpha", "2", "bad --alpha 2.0"),
        ("--counts", "0", "bad --counts [0]"),
        ("--transfer", "native", "bad --transfer 'native'; allowed: metadrive"),
        ("--transfer-test-seeds", "0", "bad --transfer-test-seeds 0"),
        ("--select", "best", "bad --select 'best'; allowed: final, validation"),
        ("--validation-episodes", "0", "bad --validation-episodes 0"),
    ]:
        assert main(["report", str(tmp_path), "--out", str(tmp_path / "o"), flag, value]) == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_report_refuses_models_of_one_scene_trained_at_two_vehicle_counts(tmp_path, capsys):
    import pandas as pd

    def table(name, trained, authors=False):
        row = dict(method="cig_td3", variant="default", trained_seed=0, test_seed=0, scenario="intersection", agent_count=trained)
        row |= dict(trained_agent_count=trained, success_rate=0.5, safety=-1.0, efficiency=1.0, checkpoint=f"/ckpt/{name}")
        rows = [row] + ([row | {"method": "coin_authors", "trained_agent_count": 30, "agent_count": 30}] if authors else [])
        path = tmp_path / name / "results.csv"
        path.parent.mkdir()
        pd.DataFrame(rows).to_csv(path, index=False)
        return path

    reduced, dense = table("reduced", 4, authors=True), table("dense", 30)
    assert main(["report", str(reduced), str(dense), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the intersection's models were trained at 2 vehicle counts: 4 vehicles" in err
    assert f"({reduced}), 30 vehicles ({dense})" in err and "report each count separately" in err
    assert not (tmp_path / "o").exists()
    # the authors' reference row (at the paper's 30) beside the 4-vehicle models is not a second training count
    from coin_app.evaluation.protocol import EvalRun, read_results
    from coin_app.evaluation.report import Sources, check_training_counts, gather

    assert len(gather([reduced]).tables) == 1
    # a sweep's models: the count its checkpoints' records name (the scene's default when they name none), against a table
    ckpt = tmp_path / "sweep" / "trial" / "checkpoint"
    ckpt.mkdir(parents=True)
    (ckpt / "coin_app.json").write_text(json.dumps({"scenario": "intersection", "env_config": {}}))  # the default: 30
    run = EvalRun("cig_td3", "default", 0, str(ckpt))
    sweep = {"path": tmp_path / "sweep", "runs": [run]}
    check_training_counts(Sources(sweeps=[sweep], tables=[{"path": dense, "table": read_results(dense)}]))  # 30 and 30
    with pytest.raises(ValueError, match=r"4 vehicles \(.*reduced.*\), 30 vehicles \(.*sweep\)"):
        check_training_counts(Sources(sweeps=[sweep], tables=[{"path": reduced, "table": read_results(reduced)}]))


def test_report_names_the_path_of_a_file_that_is_not_a_results_table(tmp_path, capsys):
    bad = tmp_path / "other.csv"
    bad.write_text("a,b\n1,2\n")
    assert main(["report", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert f"{bad} is not a coin_app results table" in capsys.readouterr().err


def test_report_lists_unreadable_trials_and_still_writes_everything_else(sweep_dir, tmp_path, capsys):
    broken = tmp_path / "broken_sweep"
    shutil.copytree(sweep_dir, broken)
    trials = {t.config["algo"]: t.path.relative_to(sweep_dir) for t in load_trials(sweep_dir)}
    result_json = broken / trials["ippo"] / "result.json"
    lines = result_json.read_text().splitlines()
    result_json.write_text("\n".join([lines[0], "{not json", *lines[1:]]) + "\n")  # a corrupt line mid-file
    progress = broken / trials["cig_td3"] / "progress.csv"
    progress.write_bytes(b'env_steps,a\n1,2\n"3,4,5\n\x00\x01')  # an unterminated quote: pandas cannot parse it
    out = tmp_path / "report"
    argv = ["report", str(broken), "--out", str(out), "--test-seeds", "1", "--tsne-samples", "20", "--tsne-episodes", "1"]
    assert main(argv) == 1  # something was left out: the exit status says so
    printed = capsys.readouterr().out
    assert "NOT EVALUATED" in printed and trials["ippo"].name in printed and "is not valid JSON" in printed
    assert f"UNREADABLE {progress}" in printed
    for name in ("results.csv", "table_main.md", "stats.csv", "report.html", "trajectories_intersection_cig_td3.png"):
        assert (out / name).is_file(), name
    # one method left: nothing is marked best, and no radar pretends to compare
    assert "**" not in (out / "table_main.md").read_text() and "<u>" not in (out / "table_main.md").read_text()
    assert not (out / "radar_intersection.png").exists() and "radar_intersection: not drawn (a radar compares methods" in printed
    page = html.unescape((out / "report.html").read_text())
    assert "Not evaluated or unreadable" in page and str(progress) in page


def test_validation_selection_scores_the_checkpoint_best_on_validation_seeds(sweep_dir, tmp_path, capsys):
    copy = tmp_path / "sweep"
    shutil.copytree(sweep_dir, copy)
    trials = {t.config["algo"]: t for t in load_trials(copy)}
    cig, ippo = trials["cig_td3"], trials["ippo"]
    # CIG-TD3's trial gets two older checkpoints: IPPO's model (index 7) and a copy of its own final one (8); final = 9
    final = cig.path / "checkpoint_000009"
    cig.final_checkpoint.rename(final)
    shutil.copytree(ippo.final_checkpoint, cig.path / "checkpoint_000007")
    shutil.copytree(final, cig.path / "checkpoint_000008")
    # the expectation from independent evaluations on the validation seeds (disjoint from the test seeds)
    seeds = validation_seeds(2)
    assert min(seeds) >= VALIDATION_SEED_BASE and max(seeds) < TEST_SEED_BASE
    runs = [EvalRun("cig_td3", "default", 0, str(c)) for c in (cig.path / "checkpoint_000007", final)]
    table = run_evaluation(runs, seeds).table
    score = {c: g["success_rate"].mean() for c, g in table.groupby("checkpoint")}
    s_ippo, s_own = score[str(cig.path / "checkpoint_000007")], score[str(final)]
    expected = cig.path / "checkpoint_000007" if s_ippo > s_own else final  # a tie (the copy and the final) goes to the later one

    out = tmp_path / "report"
    argv = ["report", str(copy), "--out", str(out), "--test-seeds", "2", "--tsne-samples", "40", "--tsne-episodes", "1"]
    assert main([*argv, "--select", "validation", "--validation-episodes", "2"]) == 0
    assert "validation-seed selection: 4 checkpoints of 2 trials, 2 validation seeds each" in capsys.readouterr().out
    chosen = pd.read_csv(out / "selection.csv")
    assert len(chosen) == 4 and chosen.groupby("trained_seed")["selected"].sum().to_dict() == {0: 2}  # one per trial
    by_ckpt = chosen[chosen["method"] == "cig_td3"].set_index("checkpoint")
    assert list(by_ckpt["order"]) == [0, 1, 2]
    # each checkpoint's metadata says how far its trial had trained (IPPO's copy keeps IPPO's count)
    assert chosen.set_index("checkpoint")["trained_env_steps"].to_dict() == {
        str(cig.path / "checkpoint_000007"): ippo.last["env_steps"],
        str(cig.path / "checkpoint_000008"): cig.last["env_steps"],
        str(final): cig.last["env_steps"],
        str(ippo.final_checkpoint): ippo.last["env_steps"],
    }
    assert (
        by_ckpt.loc[str(final), "validation_success"]
        == pytest.approx(s_own)
        == by_ckpt.loc[str(cig.path / "checkpoint_000008"), "validation_success"]
    )
    assert by_ckpt.loc[str(cig.path / "checkpoint_000007"), "validation_success"] == pytest.approx(s_ippo)
    assert by_ckpt.index[by_ckpt["selected"]].tolist() == [str(expected)]
    results = pd.read_csv(out / "results.csv")
    assert set(results.loc[results["method"] == "cig_td3", "checkpoint"]) == {str(expected)}
    assert results["test_seed"].min() >= TEST_SEED_BASE  # the selected model is scored on the test seeds only
    assert "checkpoints selected on 2 validation seeds" in (out / "table_main.md").read_text()
    # re-drawn from its results table (default --select): the caption keeps the recorded rule, selection.csv stays
    redraw = ["report", str(out / "results.csv"), "--out", str(out), "--tsne-samples", "40", "--tsne-episodes", "1"]
    assert main(redraw) == 0
    assert (out / "selection.csv").is_file() and "checkpoints selected on 2 validation seeds" in (out / "table_main.md").read_text()
    # the default protocol in the same folder: the final checkpoints, and the old choice is gone
    assert main(argv) == 0
    assert not (out / "selection.csv").exists()
    assert set(pd.read_csv(out / "results.csv").query("method == 'cig_td3'")["checkpoint"]) == {str(final)}
    assert "(final checkpoints)" in (out / "table_main.md").read_text()


def test_an_archived_sweep_is_small_evaluates_as_the_sweep_and_cannot_resume_training(sweep_dir, tmp_path, capsys):
    copy = tmp_path / "runs" / sweep_dir.name
    shutil.copytree(sweep_dir, copy)
    trials = {t.config["algo"]: t for t in load_trials(copy)}
    cig = trials["cig_td3"]
    # CIG-TD3's trial gets an older checkpoint, a copy of IPPO's model (scored apart on the validation seeds)
    final = cig.path / "checkpoint_000009"
    cig.final_checkpoint.rename(final)
    shutil.copytree(trials["ippo"].final_checkpoint, cig.path / "checkpoint_000004")
    seeds = validation_seeds(2)
    older = [EvalRun("cig_td3", "default", 0, str(c)) for c in (cig.path / "checkpoint_000004", final)]
    score = {c: g["success_rate"].mean() for c, g in run_evaluation(older, seeds, log=lambda _: None).table.groupby("checkpoint")}
    best = "checkpoint_000004" if score[older[0].checkpoint] > score[older[1].checkpoint] else final.name  # a tie: the later
    # IPPO's trial stopped short of its budget: it is named and left out
    result = trials["ippo"].path / "result.json"
    original = result.read_text()
    short = [json.loads(line) | {"done": False, "env_steps": 1} for line in original.splitlines()]
    result.write_text("".join(json.dumps(r) + "\n" for r in short))
    out = tmp_path / "archive"
    assert main(["archive", str(copy.parent), "--out", str(out), "--validation-episodes", "2", "--modules"]) == 0
    printed = capsys.readouterr().out
    assert "at the training agent count, 2 validation seeds, 1 workers" in printed  # the selection's seeds, named as such
    assert "1 trial(s) added" in printed and f"not yet: ippo-s0 (1 of {trials['ippo'].config['steps']} env steps)" in printed
    archived = load_trials(out / copy.name)
    assert [t.name for t in archived] == ["cig_td3-s0"]
    cig, kept = load_trials(copy)[0], archived[0]
    # the final and the validation-selected checkpoints, every kept one's score in selection.csv
    assert kept.config == cig.config and [c.name for c in kept.checkpoints] == sorted({best, final.name})
    chosen = pd.read_csv(kept.path / "selection.csv").set_index("checkpoint")
    assert chosen.index.tolist() == ["checkpoint_000004", final.name] and chosen.index[chosen["selected"]].tolist() == [best]
    assert chosen.loc["checkpoint_000004", "validation_success"] == pytest.approx(score[older[0].checkpoint])
    # the results without Tune's bookkeeping, otherwise the same lines; the sweep's command without its machine path
    assert kept.results == [{k: v for k, v in r.items() if k not in BOOKKEEPING} for r in cig.results]
    assert not {"hostname", "pid", "config"} & set(kept.results[-1]) and "env_steps" in kept.results[-1]
    assert str(tmp_path) not in json.loads((out / copy.name / "coin_sweep.json").read_text())["command"]
    # an actor-only copy: a few percent of the checkpoint, verified by its own manifest, evaluated exactly as the original
    kept_final = kept.path / final.name
    size = sum(p.stat().st_size for p in kept_final.rglob("*") if p.is_file())
    assert size < 0.05 * sum(p.stat().st_size for p in final.rglob("*") if p.is_file())
    assert verify(kept_final) == verify(final)
    runs = [EvalRun("cig_td3", "default", 0, str(c)) for c in (final, kept_final)]
    table = run_evaluation(runs, [TEST_SEED_BASE, TEST_SEED_BASE + 1], counts=[2], log=lambda _: None).table
    metrics = [c for c in METRIC_COLUMNS if c != "checkpoint"]
    first, second = (table[table["checkpoint"] == r.checkpoint][metrics].reset_index(drop=True) for r in runs)
    pd.testing.assert_frame_equal(first, second)
    curves = [learning_curves(table[(table["checkpoint"] == r.checkpoint) & (table["agent_count"] == 4)]) for r in runs]
    assert len(curves[0]) == len({r["env_steps"] for r in cig.results})
    pd.testing.assert_frame_equal(curves[0], curves[1])
    # training cannot go on from it, and nothing that needs the critics loads it: one line each, before any work
    assert main(["train", "--algo", "cig_td3", "--resume", str(kept_final), "--out", str(tmp_path / "t")]) == 2
    assert "holds only its metadata and exported actor" in capsys.readouterr().err
    assert main(["probe", str(kept_final), "--episodes", "1"]) == 2
    assert "holds only its exported actor" in capsys.readouterr().err
    # archiving again adds nothing and keeps what is there; an altered file is still caught
    actor = kept_final / "actor.pt"
    before = actor.read_bytes()
    assert main(["archive", str(copy), "--out", str(out), "--modules"]) == 0
    assert "0 trial(s) added" in capsys.readouterr().out and actor.read_bytes() == before
    # IPPO's trial finished, its final checkpoint still being written (no manifest yet): left for the next run
    result.write_text(original)
    manifest = trials["ippo"].final_checkpoint / "coin_app_manifest.json"
    saved = manifest.read_bytes()
    manifest.unlink()
    assert main(["archive", str(copy), "--out", str(out), "--modules"]) == 0
    steps = trials["ippo"].last["env_steps"]
    assert f"ippo-s0 (finished at {steps} env steps, its final checkpoint being written)" in capsys.readouterr().out
    manifest.write_bytes(saved)
    assert main(["archive", str(copy), "--out", str(out), "--modules"]) == 0
    assert "1 trial(s) added" in capsys.readouterr().out
    assert [t.name for t in load_trials(out / copy.name)] == ["cig_td3-s0", "ippo-s0"]
    altered = shutil.copytree(kept_final, tmp_path / "altered")
    (altered / "actor.pt").write_bytes(before[:-1] + bytes([before[-1] ^ 1]))
    with pytest.raises(ValueError, match="actor.pt fails its SHA-256 check"):
        verify(altered)
    # another run of the same protocol (other seeds, another day) joins the archive; another protocol is refused
    settings = json.loads((copy / "coin_sweep.json").read_text())
    (copy / "coin_sweep.json").write_text(json.dumps(settings | {"seeds": [9], "started": "2026-12-24 00:00:00"}))
    assert main(["archive", str(copy), "--out", str(out)]) == 0
    joined = json.loads((out / copy.name / "coin_sweep.json").read_text())
    assert joined["seeds"] == sorted({*settings["seeds"], 9}) and joined["started"] == settings["started"]
    assert [s["started"] for s in json.loads((out / copy.name / "coin_archive.json").read_text())["sources"]] == [
        settings["started"],
        "2026-12-24 00:00:00",
    ]
    (copy / "coin_sweep.json").write_text(json.dumps(settings | {"steps": 5}))
    assert main(["archive", str(copy), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "archives another sweep than" in err and "(steps differ)" in err
    # refused too: an archive inside the sweep, a bad episode count, an unknown method
    assert main(["archive", str(copy), "--out", str(copy / "inside")]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["archive", str(copy), "--out", str(tmp_path / "a2"), "--validation-episodes", "0"]) == 2
    assert "bad --validation-episodes 0" in capsys.readouterr().err
    assert main(["archive", str(copy), "--out", str(tmp_path / "a2"), "--modules", "cig_td4"]) == 2
    assert "bad --modules cig_td4; allowed: methods among" in capsys.readouterr().err
    # by default CIG-TD3 keeps its whole module (the critics, for the report's latent figure), as the original evaluates
    assert main(["archive", str(copy), "--out", str(tmp_path / "a3"), "--validation-episodes", "2"]) == 0
    with_module = load_trials(tmp_path / "a3" / copy.name)[0].path / final.name
    assert json.loads((with_module / "coin_app_manifest.json").read_text())["contents"] == "module"
    assert not (with_module / "actor.pt").exists() and type(load_module(with_module)) is type(load_module(final))
    runs = [EvalRun("cig_td3", "default", 0, str(c)) for c in (final, with_module)]
    table = run_evaluation(runs, [TEST_SEED_BASE], log=lambda _: None).table
    first, second = (table[table["checkpoint"] == r.checkpoint][metrics].reset_index(drop=True) for r in runs)
    pd.testing.assert_frame_equal(first, second)
    assert main(["train", "--algo", "cig_td3", "--resume", str(with_module), "--out", str(tmp_path / "t")]) == 2
    assert "holds only its metadata and policy module" in capsys.readouterr().err


def test_report_transfer_pairs_each_model_with_its_own_native_episodes_on_metadrive(sweep_dir, tmp_path, capsys):
    pytest.importorskip("metadrive", reason="the optional MetaDrive extra is not installed")
    out = tmp_path / "report"
    argv = ["report", str(sweep_dir), "--out", str(out), "--test-seeds", "3", "--transfer", "metadrive", "--transfer-test-seeds", "2"]
    assert main([*argv, "--tsne-samples", "40", "--tsne-episodes", "1"]) == 0
    assert "on the metadrive backend" in capsys.readouterr().out
    native, moved = pd.read_csv(out / "results.csv"), pd.read_csv(out / "transfer_results.csv")
    assert set(native["backend"]) == {"native"} and set(moved["backend"]) == {"metadrive"}
    # every model at its training count (4 agents) on the first 2 of the native test seeds
    assert (
        len(moved) == 2 * 2
        and set(moved["agent_count"]) == {4}
        and set(moved["test_seed"]) == set(sorted(native["test_seed"].unique())[:2])
    )
    table = pd.read_csv(out / "table_transfer.csv")
    for method in ("cig_td3", "ippo"):
        row = table[(table["label"] == method) & (table["metric"] == "success_rate")].iloc[0]
        shared = native[(native["method"] == method) & (native["agent_count"] == 4) & native["test_seed"].isin(moved["test_seed"])]
        assert row["n"] == 2 and row["native"] == pytest.approx(shared["success_rate"].mean())
        assert row["transfer"] == pytest.approx(moved[moved["method"] == method]["success_rate"].mean())
        assert row["gap"] == pytest.approx(row["transfer"] - row["native"])
    assert "native / metadrive (gap)" in (out / "table_transfer.md").read_text()
    assert "Transfer: native vs metadrive" in html.unescape((out / "report.html").read_text())


def test_learning_curves_keep_the_resumed_rows_of_a_trial_that_ran_steps_again(tmp_path):
    # A trial checkpointed at 1000 env steps, ran to 1500, crashed and resumed from 1000: Tune appends the
    # re-run steps, so progress.csv holds 1500 twice and 1000..1500 out of order. The curve keeps the resumed rows.
    trial = tmp_path / "trial"
    trial.mkdir()
    steps = [500, 1000, 1500, 1500, 2000]
    success = [0.1, 0.2, 0.9, 0.3, 0.4]  # 0.9 is the lost run's row at 1500
    pd.DataFrame({"env_steps": steps, "train_success_rate": success, "episode_return_mean": [1.0, 2, 3, 4, 5]}).to_csv(
        trial / "progress.csv", index=False
    )
    table = pd.DataFrame({"method": ["cig_td3"], "variant": ["default"], "trained_seed": [3], "scenario": ["intersection"]}).assign(
        checkpoint=str(trial / "checkpoint_000003")
    )
    curves = learning_curves(table)
    assert curves["env_steps"].tolist() == [500, 1000, 1500, 2000]
    assert curves["train_success_rate"].tolist() == [0.1, 0.2, 0.3, 0.4]
    assert set(curves["seed"]) == {3} and set(curves["label"]) == {"cig_td3"}


def _progress(tmp_path, name, seed, columns):
    """A trial directory with a progress.csv of ``columns`` and its one table row (the report's view of it)."""
    trial = tmp_path / name
    trial.mkdir()
    pd.DataFrame(columns).to_csv(trial / "progress.csv", index=False)
    return {"method": "itd3", "variant": "default", "trained_seed": seed, "scenario": "intersection", "checkpoint": str(trial / "c")}


def test_learning_curves_against_cpu_and_wall_time_by_hand(tmp_path):
    # seed 0: success 0.1 per CPU hour; seed 1: 0.3 per CPU hour, recorded at other times
    rows = [
        _progress(
            tmp_path, "a", 0, {"env_steps": [1, 2, 3], "train_success_rate": [0.0, 0.1, 0.2], "cpu_s": [0, 3600, 7200], "wall_s": [0, 1, 2]}
        ),
        _progress(
            tmp_path, "b", 1, {"env_steps": [1, 2], "train_success_rate": [0.0, 0.45], "cpu_s": [1800, 7200], "time_total_s": [5, 9]}
        ),
    ]
    curves = learning_curves(pd.DataFrame(rows))
    assert curves["wall_s"].tolist() == [0, 1, 2, 5, 9]  # seed 1's sweep ran before trials kept clocks: Tune's own wall time
    assert curve_axes(curves) == ["cpu_s", "wall_s"]
    x, mean, std = mean_curve(curves, "train_success_rate", points=3, x="cpu_s")
    # the grid spans what both reached (1800..7200 s); seed 0 at 1800, 4500, 7200: 0.05, 0.125, 0.2; seed 1: 0, 0.225, 0.45
    np.testing.assert_allclose(x, [1800, 4500, 7200])
    np.testing.assert_allclose(mean, [0.025, 0.175, 0.325])
    np.testing.assert_allclose(std, [0.025, 0.05, 0.125])
    assert plot_learning_curves(curves.assign(label="itd3"), tmp_path / "c.png", "intersection", {"itd3": "C0"}, "cpu_s").stat().st_size
    # a run without CPU clocks leaves that axis out
    no_cpu = learning_curves(
        pd.DataFrame([rows[0], _progress(tmp_path, "d", 2, {"env_steps": [1], "train_success_rate": [0.0], "time_total_s": [3]})])
    )
    assert curve_axes(no_cpu) == ["wall_s"]
    assert curve_axes(curves[curves["scenario"] == "roundabout"]) == []  # a scene without curves draws none


def test_training_cost_per_method_by_hand(tmp_path):
    # itd3: seeds 0 and 1 end at 2 and 1 CPU hours (3 and 2 wall hours); cig_td3 seed 0 recorded no CPU clock
    rows = [
        _progress(tmp_path, "a", 0, {"env_steps": [1, 4], "cpu_s": [10, 7200], "wall_s": [20, 10800]}),
        _progress(tmp_path, "b", 1, {"env_steps": [2, 6], "cpu_s": [5, 3600], "wall_s": [9, 7200]}),
        _progress(tmp_path, "c", 0, {"env_steps": [3], "time_total_s": [1800]}) | {"method": "cig_td3"},
    ]
    cost = training_cost(learning_curves(pd.DataFrame(rows))).set_index("label")
    assert cost.loc["itd3", ["trials", "env_steps", "cpu_h_mean", "cpu_h_min", "cpu_h_max", "cpu_h_total", "wall_h_total"]].tolist() == [
        2,
        5.0,
        1.5,
        1.0,
        2.0,
        3.0,
        5.0,
    ]
    assert np.isnan(cost.loc["cig_td3", "cpu_h_total"]) and cost.loc["cig_td3", "wall_h_total"] == 0.5
    md = write_cost(cost.reset_index(), tmp_path)[1].read_text()
    assert "| itd3 | 2 | 5 | 1.50 (1.00–2.00) | 3.00 | 5.00 |" in md and "| all | 3 | | | - | 5.50 |" in md
