"""Checkpoints: atomic saves that survive SIGKILL anywhere, a manifest every loader checks, resume that refuses a mismatch."""

import json
import os
import pickle
import random
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from fixtures import tiny_cli

from coin_app.algorithms.checkpoint_files import (
    MANIFEST_FILE,
    META_FILE,
    MODULE_PATH,
    PARTIAL_SUFFIX,
    PREVIOUS_SUFFIX,
    config_hash,
    latest_complete,
    verify,
)
from coin_app.cli import main

# A stand-in for an RLlib algorithm whose save writes several files slowly, each stamped with the
# generation it belongs to, so a checkpoint that mixes two saves is visible in its content.
SAVER = textwrap.dedent(
    """
    import pickle, sys, time
    from pathlib import Path
    import numpy as np
    from coin_app.algorithms.checkpoint_files import MODULE_PATH, save_checkpoint

    class SlowAlgo:
        gen = 0
        def save_to_path(self, path):
            path = Path(path)
            (path.joinpath(*MODULE_PATH)).mkdir(parents=True)
            for k in range(4):
                with open(path / f"part{k}.bin", "wb") as f:
                    for _ in range(8):
                        f.write(bytes([self.gen % 256]) * 32768)
                        f.flush()
                        time.sleep(0.002)
            state = {"w": np.full((1000,), self.gen % 256, np.uint8)}  # a module state (save_checkpoint records its shapes)
            (path.joinpath(*MODULE_PATH) / "module_state.pkl").write_bytes(pickle.dumps(state))

    algo, ckpt = SlowAlgo(), Path(sys.argv[1])
    algo.gen = int(sys.argv[2])  # generations keep counting across the killed processes
    while True:
        algo.gen += 1
        save_checkpoint(algo, ckpt, {"algo": "itd3", "scenario": "intersection", "overrides": {}, "env_config": {}, "gen": algo.gen})
        print(algo.gen, flush=True)
    """
)


def generation_of(checkpoint: Path) -> int:
    """The one generation all data files of a checkpoint belong to (assert: they all agree with its metadata)."""
    gen = json.loads((checkpoint / META_FILE).read_text())["gen"]
    for f in [checkpoint / f"part{k}.bin" for k in range(4)]:
        data = f.read_bytes()
        assert set(data) == {gen % 256}, f"{f} mixes generations"
    state = pickle.loads((checkpoint.joinpath(*MODULE_PATH) / "module_state.pkl").read_bytes())
    assert set(state["w"].tolist()) == {gen % 256}, "the module state mixes generations"
    return gen


def test_sigkill_at_random_points_of_repeated_saves_always_leaves_one_complete_checkpoint(tmp_path):
    script = tmp_path / "saver.py"
    script.write_text(SAVER)
    rng = random.Random(0)
    ckpt = tmp_path / "run" / "checkpoint"
    ckpt.parent.mkdir()
    last_seen = 0
    states = {"checkpoint": 0, "prev": 0}
    for _ in range(12):  # each kill lands somewhere in a save: writing files, the manifest, or between the two renames
        proc = subprocess.Popen([sys.executable, str(script), str(ckpt), str(last_seen)], stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip().isdigit()  # its first save is complete
        time.sleep(rng.uniform(0.0, 0.4))  # a save takes ~0.1 s: the kill lands in one of the next few
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        found, meta = latest_complete(ckpt)  # never raises: some complete checkpoint always exists after the first save
        gen = generation_of(found)
        assert meta["gen"] == gen
        assert gen >= last_seen  # never older than a checkpoint that was complete before
        last_seen = gen
        states["checkpoint" if found == ckpt else "prev"] += 1
        partial = ckpt.with_name("." + ckpt.name + PARTIAL_SUFFIX)
        if partial.exists():  # an interrupted save's directory is never accepted unless it is complete
            try:
                verify(partial)
            except ValueError:
                pass
            else:
                generation_of(partial)
    assert states["checkpoint"] > 0


def torn_copies(good: Path, tmp: Path) -> dict[str, Path]:
    """Copies of a good checkpoint broken in the ways a kill, a disk or a user can break one."""
    out = {}

    def copy(name: str) -> Path:
        dst = tmp / name
        shutil.copytree(good, dst)
        out[name] = dst
        return dst

    biggest = max((p for p in good.rglob("*") if p.is_file() and p.name != MANIFEST_FILE), key=lambda p: p.stat().st_size)
    rel = biggest.relative_to(good)
    with open(copy("truncated") / rel, "r+b") as f:
        f.truncate(biggest.stat().st_size // 2)
    (copy("missing_file") / rel).unlink()
    (copy("no_manifest") / MANIFEST_FILE).unlink()
    flipped = copy("flipped_byte") / rel
    data = bytearray(flipped.read_bytes())
    data[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(data))
    meta_path = copy("foreign_meta") / META_FILE
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps(meta | {"algo": "cig_td3"}))
    (copy("extra_file") / "stray.pkl").write_bytes(b"x")
    return out


TINY = [*tiny_cli("itd3", "bottleneck"), "--checkpoint-every", "1"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny ITD3 run trained through the CLI (a real checkpoint with its manifest)."""
    import ray

    out = tmp_path_factory.mktemp("ckpt") / "run"
    ray.shutdown()  # train starts its own Ray
    try:
        assert main(["train", "--algo", "itd3", "--steps", "120", "--out", str(out), *TINY]) == 0
    finally:
        ray.shutdown()
    return out


def test_train_writes_tensorboard_events_and_keeps_ray_noise_in_its_log(trained):
    events = list((trained / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1 and events[0].stat().st_size > 0
    data = events[0].read_bytes()
    assert b"env_steps" in data and b"episode_return_mean" in data and b"learner/local_critic_loss" in data
    assert (trained / "ray.log").is_file()


def test_manifest_lists_every_file_with_size_and_checksum(trained):
    ckpt = trained / "checkpoint"
    manifest = json.loads((ckpt / MANIFEST_FILE).read_text())
    meta = verify(ckpt)
    files = sorted(p.relative_to(ckpt).as_posix() for p in ckpt.rglob("*") if p.is_file() and p.name != MANIFEST_FILE)
    assert sorted(manifest["files"]) == files and META_FILE in files
    assert all(manifest["files"][f]["size"] == (ckpt / f).stat().st_size for f in files)
    assert manifest["algo"] == "itd3" and manifest["scenario"] == "bottleneck" and manifest["config_hash"] == config_hash(meta)
    assert manifest["code_version"].startswith("0.")
    assert not ckpt.with_name(ckpt.name + PREVIOUS_SUFFIX).exists()  # removed once the new one was in place
    assert not ckpt.with_name("." + ckpt.name + PARTIAL_SUFFIX).exists()


def test_every_loader_refuses_a_torn_or_altered_checkpoint_in_one_line(trained, tmp_path, capsys):
    expected = {
        "truncated": "is torn or altered",
        "missing_file": "missing",
        "no_manifest": "not a complete coin_app checkpoint",
        "flipped_byte": "fails its SHA-256 check",
        "foreign_meta": "coin_app.json has",  # the metadata is one of the checksummed files
        "extra_file": "files not in its manifest",
    }
    for name, bad in torn_copies(trained / "checkpoint", tmp_path).items():
        with pytest.raises(ValueError, match=expected[name]):
            verify(bad)
        for argv in (
            ["evaluate", str(bad), "--episodes", "1"],
            ["export", str(bad), "--out", str(tmp_path / "p.npz")],
            ["train", "--algo", "itd3", "--steps", "200", "--out", str(tmp_path / f"r_{name}"), "--resume", str(bad), *TINY],
        ):
            assert main(argv) == 2, (name, argv[0])
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and expected[name] in err and "Traceback" not in err, (name, argv[0], err)
        assert not (tmp_path / f"r_{name}").exists()  # refused before any work


def test_train_refuses_an_existing_run_and_a_mismatched_resume(trained, tmp_path, capsys):
    ckpt = trained / "checkpoint"
    argv = ["train", "--algo", "itd3", "--steps", "200", *TINY]
    assert main([*argv, "--out", str(trained)]) == 2
    assert "holds an earlier run" in capsys.readouterr().err
    cases = [
        (["--algo", "cig_td3", *TINY], "was trained by 'itd3', not 'cig_td3'"),
        ([*TINY, "--scenario", "intersection"], "was trained on scenario 'bottleneck', not 'intersection'"),
        ([a.replace("horizon=40", "horizon=50") for a in TINY], "another bottleneck config (horizon=40 there, 50 here)"),
        ([a.replace("hidden=16", "hidden=32") for a in TINY], "another network shape"),
    ]
    runs = [([*argv[: -len(TINY)], *extra], message) for extra, message in cases]  # each case's own settings in place of TINY
    # another algorithm with its own valid settings (TINY's --set keys are ITD3's: --set groups add up, unknown keys are refused first)
    runs.append((["train", "--algo", "ippo", "--steps", "200", *tiny_cli("ippo", "bottleneck")], "was trained by 'itd3', not 'ippo'"))
    for run_argv, message in runs:
        assert main([*run_argv, "--out", str(tmp_path / "new"), "--resume", str(ckpt)]) == 2, run_argv
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, (run_argv, err)
    assert not (tmp_path / "new").exists()


def test_resume_falls_back_to_the_previous_checkpoint_after_an_interrupted_rename(no_ray, trained, tmp_path, capsys):
    import ray

    run = tmp_path / "run"
    shutil.copytree(trained, run)
    ckpt = run / "checkpoint"
    ckpt.rename(ckpt.with_name(ckpt.name + PREVIOUS_SUFFIX))  # killed between the two renames of a save
    with pytest.raises(ValueError, match=r"does not exist .*the previous checkpoint is .*checkpoint\.prev"):
        verify(ckpt)
    try:
        assert main(["train", "--algo", "itd3", "--steps", "200", "--out", str(run), "--resume", str(ckpt), *TINY]) == 0
    finally:
        ray.shutdown()
    assert "resuming from the previous checkpoint" in capsys.readouterr().out
    assert verify(ckpt)["algo"] == "itd3"


def test_train_killed_at_random_points_always_resumes_from_a_complete_checkpoint(tmp_path):
    """SIGKILL a real ``train`` (a save every iteration) several times; each restart resumes from a complete checkpoint."""
    run, rng = tmp_path / "run", random.Random(3)
    ckpt = run / "checkpoint"
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "1"}
    base = [sys.executable, "-m", "coin_app", "train", "--algo", "itd3", "--out", str(run), *TINY]
    last_mtime = 0.0
    for k in range(2):  # a fresh run killed, then a resumed one (saves at random points: the saver test above kills 12 times)
        argv = [*base, "--steps", "1000000", *(["--resume", str(ckpt)] if k else [])]
        with open(tmp_path / f"train{k}.log", "w") as log:
            proc = subprocess.Popen(argv, cwd=repo, env=env, stdout=log, stderr=log, start_new_session=True)
            t0 = time.time()
            while not ((ckpt / MANIFEST_FILE).is_file() and (ckpt / MANIFEST_FILE).stat().st_mtime > last_mtime):
                assert proc.poll() is None and time.time() - t0 < 240, (tmp_path / f"train{k}.log").read_text()[-2000:]
                time.sleep(0.2)
            time.sleep(rng.uniform(0.0, 2.0))  # saves follow each other: the kill lands in one, or between two
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        found, meta = latest_complete(ckpt)  # a complete checkpoint under one of the two names, never a torn one
        assert meta["algo"] == "itd3" and found in (ckpt, ckpt.with_name(ckpt.name + PREVIOUS_SUFFIX))
        last_mtime = (found / MANIFEST_FILE).stat().st_mtime
        if k:
            assert "resumed from" in (tmp_path / f"train{k}.log").read_text()
    done = subprocess.run([*base, "--steps", "1", "--resume", str(ckpt)], cwd=repo, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "resumed from" in done.stdout, done.stdout[-2000:] + done.stderr[-2000:]
    assert verify(ckpt)["algo"] == "itd3"


def test_sigterm_stops_train_after_its_iteration_with_a_checkpoint_and_a_summary(tmp_path):
    """SIGTERM to a real ``train`` (no periodic save due): it finishes the iteration, saves, prints its summary, exits 0."""
    run = tmp_path / "run"
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-m", "coin_app", "train", "--algo", "itd3", "--out", str(run), *TINY]
    argv += ["--steps", "1000000", "--checkpoint-every", "100000"]  # the last word wins: no periodic checkpoint
    with open(tmp_path / "train.log", "w") as log:
        proc = subprocess.Popen(argv, cwd=repo, env=env, stdout=log, stderr=log, start_new_session=True)
        t0 = time.time()
        while "iter    2" not in (tmp_path / "train.log").read_text():
            assert proc.poll() is None and time.time() - t0 < 240, (tmp_path / "train.log").read_text()[-2000:]
            time.sleep(0.2)
        assert not (run / "checkpoint").exists()  # nothing saved yet
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=240)
    text = (tmp_path / "train.log").read_text()
    assert code == 0, text[-2000:]
    assert "SIGTERM: stopped after this iteration; saving a checkpoint" in text and "stopped early (SIGTERM)" in text
    summary = json.loads((run / "summary.json").read_text())
    meta = verify(run / "checkpoint")  # complete, and it says how far it trained
    assert summary["stopped"] == "SIGTERM" and 0 < summary["env_steps"] == meta["env_steps"] < 1_000_000


def test_probe_runs_on_a_trained_checkpoint_and_counts_its_vehicle_steps(trained, capsys):
    from coin_app.evaluation.critic_probe import probe_checkpoint

    probe = probe_checkpoint(trained / "checkpoint", episodes=1)
    assert 0 <= probe.stopped_steps <= probe.vehicle_steps and probe.vehicle_steps > 0
    assert list(probe.table["throttle"]) == [-1.0, 0.0, 0.5, 1.0]
    assert probe.table["global_prefers"].isna().all()  # ITD3: no global critic
    assert main(["probe", str(trained / "checkpoint"), "--episodes", "1"]) == 0
    out = capsys.readouterr().out
    assert f"{probe.stopped_steps} of {probe.vehicle_steps} vehicle-steps" in out and "summary:" in out
    assert main(["probe", str(trained / "checkpoint"), "--episodes", "0"]) == 2
    assert "bad --episodes 0; allowed: an integer >= 1" in capsys.readouterr().err


# ----------------------------------------------------------------------------- issue 60: one writer, outputs never over inputs
def _snapshot(directory: Path) -> dict[str, bytes]:
    """Every file of a directory tree with its bytes."""
    return {p.relative_to(directory).as_posix(): p.read_bytes() for p in sorted(directory.rglob("*")) if p.is_file()}


def test_resume_into_another_run_is_refused_and_overwrite_replaces_the_old_run_whole(trained, tmp_path, capsys):
    import ray

    from coin_app.training.loop import usable_cores

    other = tmp_path / "other"
    shutil.copytree(trained, other)
    before = _snapshot(other)
    argv = ["train", "--algo", "itd3", *TINY]
    assert main([*argv, "--steps", "600", "--resume", str(trained / "checkpoint"), "--out", str(other)]) == 2
    err = capsys.readouterr().err
    assert f"{other} holds an earlier run (checkpoint); --resume {trained / 'checkpoint'} would write over it" in err
    assert err.count("\n") == 1 and _snapshot(other) == before  # nothing of the other run touched
    assert main([*argv, "--steps", "600", "--resume", str(other / "checkpoint"), "--out", str(other), "--overwrite"]) == 2
    assert "--overwrite would delete" in capsys.readouterr().err and _snapshot(other) == before
    old_events = {p.name for p in (other / "tensorboard").iterdir()}
    threads = usable_cores() + 1
    try:
        assert main([*argv, "--steps", "60", "--out", str(other), "--overwrite", "--threads", str(threads)]) == 0
    finally:
        ray.shutdown()
    out = capsys.readouterr().out
    assert "--overwrite: the earlier run's checkpoint, summary.json, config.json, tensorboard, ray.log deleted" in out
    assert f"warning: --threads {threads} > the {usable_cores()} CPU cores this process may use" in out
    assert "warning: --steps 60 <= warmup_steps 60: every action is uniform random and the networks are never updated" in out
    events = {p.name for p in (other / "tensorboard").iterdir()}
    assert len(events) == 1 and not events & old_events  # the old run's TensorBoard events went with it
    summary = json.loads((other / "summary.json").read_text())
    per_iteration = summary["env_steps"]  # one iteration: the budget of 60 (TINY's warm-up) is below one batch
    assert summary["iterations"] == 1 and per_iteration > 60
    note = f"trained {per_iteration} env steps, more than the 60 asked for: an iteration samples {per_iteration} env steps at once"
    assert summary["note"].startswith(note) and f"note: {note}" in out


def test_a_checkpoint_on_another_scene_is_evaluated_with_the_warning(trained, capsys):
    ckpt = trained / "checkpoint"
    assert main(["evaluate", str(ckpt), "--scenario", "intersection", "--num-agents", "3", "--set", "horizon=5", "--episodes", "1"]) == 0
    captured = capsys.readouterr()
    warning = f"warning: {ckpt} was trained on bottleneck, not intersection: a scene it was not trained for"
    assert captured.err.splitlines() == [warning] and f"  {warning}" in captured.out


def test_a_checkpoint_is_checked_against_its_manifest_version_and_its_recorded_shapes(trained, tmp_path, capsys):
    from coin_app.algorithms.checkpoint_files import SHAPES_KEY, module_shapes, write_manifest

    good = trained / "checkpoint"
    meta = verify(good)
    assert {k: tuple(v) for k, v in meta[SHAPES_KEY].items()} == module_shapes(good) and "actor.net.0.weight" in meta[SHAPES_KEY]
    # a manifest of a format this code does not read
    future = tmp_path / "future"
    shutil.copytree(good, future)
    manifest = json.loads((future / MANIFEST_FILE).read_text())
    (future / MANIFEST_FILE).write_text(json.dumps(manifest | {"version": 99}))
    with pytest.raises(ValueError, match=r"its manifest has format version 99, this code reads version\(s\) 1"):
        verify(future)
    assert main(["evaluate", str(future), "--episodes", "1"]) == 2
    assert "format version 99" in capsys.readouterr().err
    # metadata (re-manifested, so only the shapes disagree) recording another network than its tensors
    shapes = {**meta[SHAPES_KEY], "actor.net.0.weight": [17, 91]}
    other = tmp_path / "other"
    shutil.copytree(good, other)
    (other / META_FILE).write_text(json.dumps(meta | {SHAPES_KEY: shapes}))
    write_manifest(other, meta | {SHAPES_KEY: shapes})
    with pytest.raises(ValueError, match=r"its tensors are not the network its metadata records \(actor.net.0.weight: \(17, 91\)"):
        verify(other)


def test_resume_compares_the_recorded_shapes_with_what_this_code_builds(trained, monkeypatch, capsys, tmp_path):
    from coin_app.algorithms.checkpoint_files import SHAPES_KEY
    from coin_app.training import check_resume

    meta = verify(trained / "checkpoint")
    overrides = dict(meta["overrides"])
    check_resume(trained / "checkpoint", meta, "itd3", "bottleneck", overrides)  # the same code: accepted
    grown = meta | {SHAPES_KEY: {**meta[SHAPES_KEY], "actor.net.0.weight": [32, 91]}}  # as if a default had changed since
    with pytest.raises(ValueError, match=r"another network shape \(actor.net.0.weight: \(32, 91\) there, \(16, 91\) here"):
        check_resume(trained / "checkpoint", grown, "itd3", "bottleneck", overrides)


def test_export_into_its_own_checkpoint_is_refused_and_the_checkpoint_stays_loadable(trained, capsys):
    ckpt = trained / "checkpoint"
    before = _snapshot(ckpt)
    assert main(["export", str(ckpt), "--out", str(ckpt / "policy.npz")]) == 2
    err = capsys.readouterr().err
    assert "is, or is inside, the checkpoint it exports" in err and err.count("\n") == 1
    assert _snapshot(ckpt) == before and verify(ckpt)["algo"] == "itd3"


def test_two_trains_on_one_out_started_together_exactly_one_runs(tmp_path):
    """Two real ``train`` processes on one --out at once: one trains, the other is refused naming the first's PID."""
    run = tmp_path / "run"
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-m", "coin_app", "train", "--algo", "itd3", "--out", str(run), *TINY, "--steps", "1500"]
    procs = [subprocess.Popen(argv, cwd=repo, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=600) for p in procs]
    codes = sorted(p.returncode for p in procs)
    assert codes == [0, 2], outs
    winner, loser = (0, 1) if procs[0].returncode == 0 else (1, 0)
    err = outs[loser][1].strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {run} is being written by PID {procs[winner].pid} on "), err
    assert "python -m coin_app train --algo itd3" in err[0]
    assert verify(run / "checkpoint")["algo"] == "itd3" and json.loads((run / "summary.json").read_text())["env_steps"] >= 1500
    assert not list(tmp_path.glob(".run.lock"))  # released (and removed) at the end


def _train_until(tmp_path: Path, marker: str, name: str) -> tuple[subprocess.Popen, Path, Path]:
    """A real ``train`` in its own process group, once its log shows ``marker``: (process, run directory, log)."""
    run, log_path = tmp_path / name, tmp_path / f"{name}.log"
    repo = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(repo), "OMP_NUM_THREADS": "1"}
    argv = [sys.executable, "-m", "coin_app", "train", "--algo", "itd3", "--out", str(run), *TINY, "--steps", "1000000"]
    argv += ["--checkpoint-every", "100000"]  # the last word wins: no periodic checkpoint
    with open(log_path, "w") as log:
        proc = subprocess.Popen(argv, cwd=repo, env=env, stdout=log, stderr=log, start_new_session=True)
    t0 = time.time()
    while marker not in log_path.read_text():
        assert proc.poll() is None and time.time() - t0 < 240, log_path.read_text()[-2000:]
        time.sleep(0.05)
    return proc, run, log_path


@pytest.mark.parametrize(
    ("sig", "marker", "group"),
    [(signal.SIGINT, "sampling:", False), (signal.SIGTERM, "sampling:", True), (signal.SIGTERM, "train:", True)],
    ids=["SIGINT while the algorithm is built", "SIGTERM to the group then", "SIGTERM to the group in Ray's start-up"],
)
def test_a_signal_during_start_up_stops_train_at_once_with_its_code(tmp_path, sig, marker, group):
    """Ctrl-C or a scheduler's SIGTERM (to the process or its whole group) before the first iteration: exit 128 + signal
    (130, 143) in one line, no checkpoint (nothing trained). It used to be ignored, or to end in exit 1 after a minute."""
    proc, run, log_path = _train_until(tmp_path, marker, "run")
    (os.killpg if group else os.kill)(proc.pid, sig)
    t0 = time.time()
    code = proc.wait(timeout=120)
    text = log_path.read_text()
    assert code == 128 + sig, text[-2000:]
    assert f"interrupted: {sig.name} during start-up: stopped before any training (no checkpoint was due)" in text
    assert "Traceback" not in text and not (run / "checkpoint").exists() and time.time() - t0 < 90


def test_sigterm_to_the_process_group_stops_train_after_its_iteration_with_a_checkpoint(tmp_path):
    """SIGTERM to the whole group (the local Ray's GCS and raylet included): the iteration ends, a checkpoint, exit 0.
    Before, the group's SIGTERM killed the GCS and the run hung 60 s on it, then exited 1."""
    proc, run, log_path = _train_until(tmp_path, "iter    2", "run")
    os.killpg(proc.pid, signal.SIGTERM)
    code = proc.wait(timeout=240)
    text = log_path.read_text()
    assert code == 0, text[-2000:]
    assert "SIGTERM: stopped after this iteration; saving a checkpoint" in text and "stopped early (SIGTERM)" in text
    summary = json.loads((run / "summary.json").read_text())
    assert summary["stopped"] == "SIGTERM" and summary["env_steps"] == verify(run / "checkpoint")["env_steps"] > 0
