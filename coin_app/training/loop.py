"""The train loop: RLlib iterations until an env-step or wall-time budget or a signal, with checkpoints and one line per iteration."""

from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import ray
import torch
from tensorboardX import SummaryWriter

from coin_app.adapters.batched_runner import BatchedEnvRunner
from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import check_resumable, latest_complete
from coin_app.algorithms.common import ProgressReporting, scenario_config_of
from coin_app.evaluation.limits import CONNECT_TIMEOUT_S, check_train_budget
from coin_app.evaluation.outputs import OutputLock, write_text_atomic
from coin_app.training.address import check_address
from coin_app.training.checkpoints import check_resume, check_run_dir, checkpoint_meta, clear_run, save
from coin_app.training.config import build_config
from coin_app.training.monitor import (
    CRITIC_LOSS_KEYS,
    EVAL_RESULT_KEY,
    FreezeDetector,
    RunProgress,
    _eval_line,
    iteration_metrics,
    outcome_text,
    process_tree_cpu_seconds,
    ray_noise_to,
)

TENSORBOARD_DIR = "tensorboard"  # the iteration metrics of a train run as TensorBoard event files, in its --out


RAY_LOG = "ray.log"  # Ray's and RLlib's log records and Python warnings of a train run, in its --out


# summary["stopped"], or the name of the signal
STOPPED_AT_BUDGET, STOPPED_AT_MAX_MINUTES, STOPPED_AT_MAX_CPU = "steps", "max_minutes", "max_cpu_hours"


class Interrupted(KeyboardInterrupt):
    """A stop at once by a signal: during start-up (nothing trained, nothing to save) or a second signal in the loop."""

    def __init__(self, signal_name: str, message: str):
        super().__init__(message)
        self.signal_name = signal_name
        self.exit_code = 128 + int(signal.Signals[signal_name])  # the shell's convention: 130 for SIGINT, 143 for SIGTERM

    @classmethod
    def at_startup(cls, signal_name: str) -> Interrupted:
        """The stop of a signal received before the first iteration."""
        return cls(signal_name, f"{signal_name} during start-up: stopped before any training (no checkpoint was due)")


class RunClock:
    """A run's cumulative clocks over its segments (a fresh start and each resume): ``cpu_s``, CPU seconds of this process
    and the processes it started (its local Ray's too) since the clock was made, and ``wall_s``, wall seconds since then;
    each plus the resumed checkpoint's figures (its metadata's ``cpu_s`` and ``wall_s``; 0 for a fresh run)."""

    def __init__(self, resumed: dict[str, Any] | None = None):
        resumed = resumed or {}
        self.cpu_before, self.wall_before = float(resumed.get("cpu_s", 0.0)), float(resumed.get("wall_s", 0.0))
        self.cpu_start, self.wall_start = process_tree_cpu_seconds(), time.perf_counter()

    def read(self) -> dict[str, float]:
        """``{"cpu_s": ..., "wall_s": ...}`` now, the earlier segments included."""
        cpu = self.cpu_before + process_tree_cpu_seconds() - self.cpu_start
        return {"cpu_s": round(cpu, 3), "wall_s": round(self.wall_before + time.perf_counter() - self.wall_start, 3)}


class StopRequest:
    """Set by SIGTERM or SIGINT while :func:`stop_on_signal` is active: the run stops after its current iteration."""

    def __init__(self) -> None:
        self.signal: str | None = None  # the name of the first signal received in the loop
        self.started = False  # the loop has begun: a first signal asks for a stop after the iteration (before: at once)
        self.startup_signal: str | None = None  # a signal received during start-up
        self.install: Callable[[], None] = lambda: None  # (re)installs the handlers (Ray's init sets its own SIGTERM handler)


@contextmanager
def stop_on_signal() -> Iterator[StopRequest]:
    """While inside (main thread), SIGTERM and SIGINT are honoured: during start-up (``started`` False) they stop at once
    (:class:`Interrupted`); in the loop the first asks for a stop after the current iteration, a second stops at once."""
    request = StopRequest()

    def handler(signum: int, frame: Any) -> None:  # sets the flag or raises: printing here could re-enter a write to stdout
        name = signal.Signals(signum).name
        if not request.started:
            request.startup_signal = name  # also seen at the loop's start, should the exception be caught on its way
            raise Interrupted.at_startup(name)
        if request.signal is not None:
            raise Interrupted(name, f"second {name}: stopped at once (the last checkpoint is kept)")
        request.signal = name

    if threading.current_thread() is not threading.main_thread():  # handlers can only be set there; signals keep their default
        yield request
        return
    previous = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}

    def install() -> None:
        for s in previous:
            signal.signal(s, handler)

    request.install = install
    install()
    try:
        yield request
    finally:
        for s, h in previous.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def train(
    name: str,
    scenario: str,
    steps: int,
    seed: int,
    overrides: dict[str, Any],
    out: Path,
    checkpoint_every: int = 10,
    resume: Path | None = None,
    log: Callable[[str], None] = print,
    max_minutes: float | None = None,
    threads: int = 1,
    address: str | None = None,
    overwrite: bool = False,
    progress: bool | None = None,
    connect_timeout: float = CONNECT_TIMEOUT_S,
    command: str | None = None,
    max_cpu_hours: float | None = None,
) -> dict[str, Any]:
    """Train for ``steps`` env steps, ``max_minutes`` of wall time (this segment) or ``max_cpu_hours`` of the run's CPU time
    (every segment, :class:`RunClock`), whichever ends first; checkpoints every ``checkpoint_every`` iterations and at the end.

    ``threads``: torch threads of this process (its learner and local env runner; one by default,
    as every Ray worker gets). ``address``: a running Ray cluster to use instead of a local session
    over all of this machine's cores, refused after ``connect_timeout`` seconds if it cannot be reached.
    ``out`` has one writer (:class:`~coin_app.evaluation.outputs.OutputLock`, naming ``command``);
    it must not hold another run unless ``overwrite`` (which deletes that run's files first) or
    ``resume`` is that run's own checkpoint; ``resume`` must be a complete checkpoint (or its
    ``.prev``, after an interrupted save) of the same algorithm, scenario config and network shape.
    Everything is checked before any work starts. SIGINT / SIGTERM: see :func:`stop_on_signal`.
    ``progress``: the progress bar (``None``: on a terminal only; see ``RunProgress``).
    Every iteration's metrics, checkpoint and the summary carry the run's ``cpu_s`` and ``wall_s`` (:class:`RunClock`).
    """
    check_train_budget(steps, max_minutes, checkpoint_every, threads, max_cpu_hours)
    check_address(address, connect_timeout)  # an unreachable cluster ends here, in one line, after connect_timeout (Ray running or not)
    out = Path(out)
    with stop_on_signal() as stop:
        cfg = build_config(name, scenario, overrides, seed)
        resume_meta: dict[str, Any] = {}
        if resume is not None:
            found, resume_meta = latest_complete(resume)
            if found != resume:
                log(f"{resume} is incomplete (a save was interrupted); resuming from the previous checkpoint {found}")
            resume = found
            check_resumable(resume)
            check_resume(resume, resume_meta, name, scenario, overrides)
        clock = RunClock(resume_meta)  # from here: the run's CPU (its Ray session's included) and wall time
        with OutputLock(out, command, "the run directory") as lock:
            if lock.stale_note():
                log(str(lock.stale_note()))
            check_run_dir(out, resume, overwrite)
            if overwrite:
                removed = clear_run(out)
                if removed:
                    log(f"--overwrite: the earlier run's {', '.join(removed)} deleted from {out}")
            spec = registry.get(name)
            warmup = cfg.warmup_steps if "warmup_steps" in spec.hyperparameters else 0
            if warmup and steps <= warmup:
                log(
                    f"warning: --steps {steps} <= warmup_steps {warmup}: every action is uniform random and the networks are never "
                    f"updated (losses print nan). Train longer, or --set warmup_steps=N; small settings that learn in minutes: --quick"
                )
            cores = usable_cores()
            if threads > cores:
                log(f"warning: --threads {threads} > the {cores} CPU cores this process may use; extra torch threads only slow it down")
            torch.set_num_threads(threads)
            if not ray.is_initialized():
                with sigterm_blocked_in_children():  # a SIGTERM to the process group leaves the local Ray to this run's own stop
                    try:
                        ray.init(address=address or "local", include_dashboard=False, log_to_driver=False, configure_logging=False)
                    except SystemExit as exc:  # Ray's init answers a SIGTERM with sys.exit(15): the same stop as ours
                        if exc.code != int(signal.SIGTERM):
                            raise
                        raise Interrupted.at_startup("SIGTERM") from None
                    stop.install()  # Ray's init set its own SIGTERM handlers (Python's and a native one): ours again, before
                    # a SIGTERM held during the init is delivered
                where = f"the cluster at {address}" if address else "a local session (all of this machine's cores)"
                resources = ray.cluster_resources()
                log(f"ray: {where} with {int(resources.get('CPU', 0))} CPUs, {int(resources.get('GPU', 0))} GPUs")
            return _run(cfg, spec, name, scenario, steps, seed, overrides, out, checkpoint_every, resume, log, max_minutes, warmup,
                        progress, stop, clock, max_cpu_hours)  # fmt: skip


def _run(
    cfg: Any,
    spec: Any,
    name: str,
    scenario: str,
    steps: int,
    seed: int,
    overrides: dict[str, Any],
    out: Path,
    checkpoint_every: int,
    resume: Path | None,
    log: Callable[[str], None],
    max_minutes: float | None,
    warmup: int,
    progress: bool | None,
    stop: StopRequest,
    clock: RunClock,
    max_cpu_hours: float | None = None,
) -> dict[str, Any]:
    """The run itself, once everything is checked and ``out`` is locked (see :func:`train`)."""
    runner = "batched" if cfg.env_runner_cls is BatchedEnvRunner else "RLlib's multi_agent"
    log(
        f"sampling: {runner} env runner, {max(1, cfg.num_env_runners)} runner(s) x {cfg.num_envs_per_env_runner} env(s); "
        f"learner: {'remote' if cfg.num_learners else 'in this process'}, {torch.get_num_threads()} torch thread(s) here"
    )
    with ray_noise_to(out / RAY_LOG):  # Ray's and RLlib's log records and warnings: a file, not the console
        algo = cfg.build_algo()
        if resume is not None:
            algo.restore_from_path(str(resume.resolve()))
            log(f"resumed from {resume}")
        meta = checkpoint_meta(name, scenario, seed, overrides)
        write_text_atomic(out / "config.json", json.dumps(meta, indent=2, default=str))
        if spec.capabilities.joint_replay:
            agents = scenario_config_of(cfg).num_agents
            log(f"replay: {cfg.replay_capacity:,} agent transitions, about {cfg.replay_capacity // agents:,} env steps at {agents} agents")
        # the TD3 family's full-brake freeze (its advice names their keys); a PPO policy creeps early by design
        freeze = None if spec.capabilities.on_policy else FreezeDetector(warmup)
        board = SummaryWriter(str(out / TENSORBOARD_DIR))  # what Tune trials write too: tensorboard --logdir <out>
        t0 = time.perf_counter()
        start = sampled = int(algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0))
        result: dict[str, Any] = {}
        last_eval: dict[str, float] = {}
        ckpt = out / "checkpoint"
        bar = RunProgress(steps, start, log, progress)
        if isinstance(algo, ProgressReporting):  # long iterations: their updates are shown as they go
            algo.progress_callback = bar.phase
        stopped = STOPPED_AT_BUDGET  # why the loop ended: the budget, max_minutes, max_cpu_hours or a signal's name
        saved = None  # env steps of the newest checkpoint written by this run
        per_iteration = 0  # env steps the first iteration sampled (an iteration's batch)

        def save_at(env_steps: int) -> int:
            bar.phase("saving checkpoint", 0, 0)
            save(algo, ckpt, meta | {"env_steps": int(env_steps)} | clock.read())
            return env_steps

        try:
            stop.started = True  # from here a first signal stops after the current iteration, with a checkpoint
            if stop.startup_signal is not None:
                name = stop.startup_signal
                raise Interrupted.at_startup(name)
            while sampled < steps and stop.signal is None:
                if max_minutes is not None and time.perf_counter() - t0 >= 60.0 * max_minutes:
                    stopped = STOPPED_AT_MAX_MINUTES
                    break
                if max_cpu_hours is not None and clock.read()["cpu_s"] >= 3600.0 * max_cpu_hours:
                    stopped = STOPPED_AT_MAX_CPU
                    break
                result = algo.train()
                m = iteration_metrics(result) | clock.read()
                per_iteration = per_iteration or m["env_steps"] - sampled
                sampled = m["env_steps"]
                bar.advance(sampled)
                it = int(result["training_iteration"])
                elapsed = time.perf_counter() - t0
                critic = next((m[k] for k in CRITIC_LOSS_KEYS if k in m), np.nan)
                bar.say(
                    f"iter {it:>4}  env steps {sampled:>8}  {(sampled - start) / max(elapsed, 1e-9):7.1f} steps/s  "
                    f"episode return {m['episode_return_mean']:8.2f}  critic loss {critic:8.4f}"
                    + outcome_text(m)
                    + f"  cpu {m['cpu_s'] / 3600:.3f} h"
                )
                for key, value in m.items():
                    if math.isfinite(value):
                        board.add_scalar(key, value, global_step=sampled)
                board.flush()
                warning = freeze.update(m) if freeze is not None else None
                if warning:
                    bar.say(warning)
                if EVAL_RESULT_KEY in result:
                    last_eval = result[EVAL_RESULT_KEY]
                    bar.say(_eval_line(last_eval))
                if it % checkpoint_every == 0:
                    saved = save_at(sampled)
            if stop.signal is not None and sampled < steps:  # a signal during the last iteration changes nothing
                stopped = stop.signal
                bar.say(f"{stop.signal}: stopped after this iteration; saving a checkpoint (send it again to stop at once)")
            if saved != sampled:  # the last iteration's periodic save already holds this state
                save_at(sampled)
        finally:
            bar.close()
        board.close()
        algo.stop()
    summary = {
        "checkpoint": str(ckpt),
        "ray_log": str(out / RAY_LOG),
        "tensorboard": str(out / TENSORBOARD_DIR),
        "env_steps": sampled,
        "iterations": int(result.get("training_iteration", 0)),
        "wall_s": round(time.perf_counter() - t0, 1),
        "run_cpu_s": clock.read()["cpu_s"],  # every segment of the run (resumed ones too), its Ray session's processes included
        "run_wall_s": clock.read()["wall_s"],
        "eval": last_eval,
        "stopped": stopped,
    }
    if sampled > steps and stopped == STOPPED_AT_BUDGET:
        summary["note"] = (
            f"trained {sampled} env steps, more than the {steps} asked for: an iteration samples {per_iteration} env steps at once "
            "(its batch) and the budget is checked between iterations"
        )
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=2))
    return summary


@contextmanager
def sigterm_blocked_in_children() -> Iterator[None]:
    """While inside, SIGTERM is blocked in this thread, so the processes started here (a local Ray's GCS, raylet and
    workers) inherit it blocked, as Ray's own processes inherit SIGINT blocked (``ray._private.services``).

    A terminal or a scheduler signals a whole process group: unblocked, the GCS died with the driver's first SIGTERM and
    the driver hung 60 s on it, then exited 1 without its checkpoint. Ray still stops these processes at shutdown (SIGKILL
    after a second), and they end with this process (Ray's fate sharing). This process still takes a SIGTERM at once: a
    helper thread started before the block keeps it unblocked, the kernel delivers it there, and Python runs the handler in
    the main thread at its next step.
    """
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    done = threading.Event()
    receiver = threading.Thread(target=done.wait, name="sigterm-receiver", daemon=True)
    receiver.start()  # its signal mask is the main thread's before the block: SIGTERM open
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)
        done.set()


def usable_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS
        return os.cpu_count() or 1
