"""Training: the validated config of a run, the train loop, checkpoints, iteration metrics and periodic evaluation.

``build_config`` is where a run is set up: the seed is checked, ``--set`` overrides are routed
(``registry.split_overrides``), the scenario config is parsed **once** into a frozen
``ScenarioConfig`` / ``ArenaConfig`` and handed to the algorithm's spec, and the callbacks
every run gets are attached (agent outcomes; periodic evaluation for algorithms that declare
it). ``train`` runs RLlib iterations until an env-step or wall-time budget, logs one line per
iteration and writes coin_app checkpoints (RLlib's layout plus ``coin_app.json``).
"""

from __future__ import annotations

import json
import logging
import math
import signal
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import ray
import torch
from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.callbacks.callbacks import RLlibCallback
from ray.rllib.core.rl_module.rl_module import RLModule
from tensorboardX import SummaryWriter
from tqdm import tqdm

from coin_app.adapters.batched_runner import BatchedEnvRunner
from coin_app.adapters.rllib_env import make_env, register_envs
from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import PREVIOUS_SUFFIX, latest_complete, save_checkpoint
from coin_app.algorithms.checkpoints import actor_policy
from coin_app.algorithms.common import SHARED_MODULE_ID, AgentOutcomes, ProgressReporting, scenario_config_of
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.metrics import aggregate
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.scenarios import config_from_dict
from coin_app.sim.seeds import check_training_seed, validation_seeds

EVAL_RESULT_KEY = "coin_eval"  # the periodic evaluation's metrics in an iteration's result
TENSORBOARD_DIR = "tensorboard"  # the iteration metrics of a train run as TensorBoard event files, in its --out
RAY_LOG = "ray.log"  # Ray's and RLlib's log records and Python warnings of a train run, in its --out
# the critic loss an iteration line shows, the first present: TD3 family (CIG-TD3/ITD3, TraCo), then the PPO family
CRITIC_LOSS_KEYS = ("learner/local_critic_loss", "learner/domain_critic_loss", "learner/vf_loss")


class RunProgress:
    """The train loop's progress display: a tqdm bar over env steps, showing the phase inside the current iteration.

    ``enabled``: ``None`` shows the bar only on a terminal (a log file gets the iteration lines
    alone); ``True`` always; ``False`` never. Log lines are written around the bar.
    """

    def __init__(self, steps: int, start: int, log: Callable[[str], None], enabled: bool | None = None):
        self.bar = tqdm(
            total=steps, initial=min(start, steps), unit="step", unit_scale=True, desc="train", leave=False, dynamic_ncols=True,
            disable=None if enabled is None else not enabled,
        )  # fmt: skip
        self.log = log
        self._shown = 0.0

    def say(self, line: str) -> None:
        """Log one line without tearing the bar."""
        if self.bar.disable:
            self.log(line)
        else:
            with tqdm.external_write_mode():
                self.log(line)

    def phase(self, phase: str, done: int, total: int) -> None:
        """Show how far the current iteration's phase is (at most twice a second)."""
        now = time.monotonic()
        if self.bar.disable or now - self._shown < 0.5:
            return
        self._shown = now
        self.bar.set_postfix_str(f"{phase} {done}/{total}" if total else phase, refresh=False)
        self.bar.refresh()

    def advance(self, sampled: int) -> None:
        """Move the bar to ``sampled`` env steps."""
        self.bar.update(max(0, min(sampled, self.bar.total) - self.bar.n))

    def close(self) -> None:
        """Remove the bar."""
        self.bar.close()


@contextmanager
def ray_noise_to(path: Path) -> Iterator[None]:
    """While inside, Ray's and RLlib's log records (``ray`` loggers) and Python warnings go to ``path``, not the console."""
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    loggers = [logging.getLogger(name) for name in ("ray", "ray.rllib", "py.warnings")]  # ray.rllib has its own handler
    saved = [(lg, lg.handlers[:], lg.propagate) for lg in loggers]
    for lg in loggers:
        lg.handlers, lg.propagate = [handler], False
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # each distinct warning once, into the file
        logging.captureWarnings(True)
        try:
            yield
        finally:
            logging.captureWarnings(False)
            for lg, handlers, propagate in saved:
                lg.handlers, lg.propagate = handlers, propagate
            handler.close()


def build_config(name: str, scenario: str, overrides: dict[str, Any], seed: int) -> AlgorithmConfig:
    """A validated RLlib config of algorithm ``name`` on ``scenario`` (the scenario config parsed once)."""
    spec = registry.get(name)
    check_training_seed(seed)
    if scenario not in spec.scenarios:
        raise ValueError(f"{name} does not train on scenario {scenario!r}; allowed: {', '.join(spec.scenarios)}")
    env_cfg, algo_cfg = registry.split_overrides(name, overrides, scenario)
    run = registry.split_run_settings(algo_cfg)
    scenario_config = config_from_dict(scenario, {**spec.scenario_defaults(algo_cfg), **env_cfg})  # refuses bad values before any work
    callbacks: list[type[RLlibCallback]] = [AgentOutcomes]
    if spec.capabilities.periodic_evaluation:
        callbacks.append(PeriodicEvaluation)
    cfg = spec.build_config(scenario_config, algo_cfg, seed).callbacks(callbacks)
    cfg = with_env_runner(cfg, run.env_runner, run.num_envs_per_env_runner, spec.capabilities.on_policy, scenario_config)
    if run.num_learners or run.num_gpus_per_learner:
        cfg = cfg.learners(num_learners=run.num_learners, num_gpus_per_learner=run.num_gpus_per_learner)
    notice = logging.getLogger("ray.rllib.algorithms.algorithm_config")  # "You are running X on the new API stack!" (once)
    level = notice.level
    notice.setLevel(logging.ERROR)
    try:
        cfg.validate()
    finally:
        notice.setLevel(level)
    register_envs()  # the coin-<scenario>-v0 names the config refers to
    return cfg


def with_env_runner(
    cfg: AlgorithmConfig, runner: str, num_envs: int | str, on_policy: bool, scenario: ScenarioConfig | ArenaConfig
) -> AlgorithmConfig:
    """``cfg`` sampling with ``runner`` and ``num_envs`` envs per env runner (the ``env_runner`` keys of ``registry.RUNNER_KEYS``)."""
    backend = scenario.backend if isinstance(scenario, ScenarioConfig) else "native"
    if runner == "auto":
        runner = "batched" if backend == "native" else "multi_agent"
    if runner == "batched" and backend != "native":
        raise ValueError(f"env_runner='batched' steps the native simulator, not backend {backend!r}; allowed: env_runner='multi_agent'")
    if num_envs == "auto":
        num_envs = 1
        fragment = cfg.rollout_fragment_length
        if on_policy and runner == "batched":  # the whole train batch in one sampling round
            per_round = (fragment if isinstance(fragment, int) else 200) * max(1, cfg.num_env_runners)
            num_envs = max(1, cfg.total_train_batch_size // per_round)
    cfg = cfg.env_runners(num_envs_per_env_runner=num_envs)
    if runner == "batched":
        cfg = cfg.env_runners(env_runner_cls=BatchedEnvRunner)
    return cfg


def fresh_module(name: str, scenario: str | None = None, overrides: dict[str, Any] | None = None, seed: int = 0) -> RLModule:
    """An untrained shared RLModule of algorithm ``name`` as its config builds it (no Ray session needed)."""
    scenario = scenario or registry.get(name).scenarios[0]
    cfg = build_config(name, scenario, dict(overrides or {}), seed)
    env = make_env(scenario, cfg.env_config)
    agent = env.possible_agents[0]
    spaces = {SHARED_MODULE_ID: (env.observation_spaces[agent], env.action_spaces[agent])}
    env.close()
    return cfg.get_multi_rl_module_spec(spaces=spaces).build()[SHARED_MODULE_ID]


def _learner_policy(learner: Any) -> Any:
    """The evaluation policy of a learner's shared module (CoPO: LCFs as the module's ``evaluation_lcf`` says)."""
    return actor_policy(learner.module[SHARED_MODULE_ID].unwrapped())


def evaluate_algorithm(algo: Algorithm, seeds: list[int]) -> dict[str, float]:
    """Mean metrics of an algorithm's current deterministic actor (the learner's) on ``seeds`` (either backend)."""
    policy = next(iter(algo.learner_group.foreach_learner(_learner_policy))).get()
    per_episode = evaluate_policy(policy, scenario_config_of(algo.config), seeds)
    return {k: v["mean"] for k, v in aggregate(per_episode).items()}


class PeriodicEvaluation(RLlibCallback):
    """Every ``eval_every`` iterations, the deterministic actor on ``eval_episodes`` validation seeds (``result["coin_eval"]``)."""

    def on_train_result(self, *, algorithm: Algorithm, result: dict, **kwargs: Any) -> None:
        """Add the periodic evaluation to this iteration's result when it is due."""
        every = algorithm.config.eval_every
        if every and result["training_iteration"] % every == 0:
            result[EVAL_RESULT_KEY] = evaluate_algorithm(algorithm, validation_seeds(algorithm.config.eval_episodes))


def iteration_metrics(result: dict[str, Any]) -> dict[str, float]:
    """The flat per-iteration figures coin_app logs and reports to Tune, from an RLlib ``algo.train()`` result.

    ``env_steps``, ``episode_return_mean``, ``episode_len_mean``, the agent outcomes of the
    iteration (``agents_finished``, ``train_success_rate``, ``train_collision_rate``; NaN when
    no agent ended), the acting vehicles' ``mean_speed`` (m/s; NaN without driving agents),
    every scalar learner metric of the shared module (``learner/<name>``) and
    the last periodic evaluation on validation seeds (``eval/<metric>``), if any.
    """
    runners = result.get("env_runners", {})
    sampled = result.get("num_env_steps_sampled_lifetime", runners.get("num_env_steps_sampled_lifetime", 0))
    finished = float(runners.get("agents_finished", 0) or 0)
    agent_steps = float(runners.get("agents_agent_steps", 0) or 0)
    out = {
        "env_steps": int(sampled),
        "episode_return_mean": float(runners.get("episode_return_mean", float("nan"))),
        "episode_len_mean": float(runners.get("episode_len_mean", float("nan"))),
        "agents_finished": finished,
        "train_success_rate": runners.get("agents_succeeded", 0) / finished if finished else float("nan"),
        "train_collision_rate": runners.get("agents_collided", 0) / finished if finished else float("nan"),
        "mean_speed": runners.get("agents_speed_sum", 0.0) / agent_steps if agent_steps else float("nan"),
    }
    for key, value in result.get("learners", {}).get(SHARED_MODULE_ID, {}).items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            out[f"learner/{key}"] = float(value)
    for key, value in result.get(EVAL_RESULT_KEY, {}).items():
        out[f"eval/{key}"] = float(value)
    return out


COLLAPSED_ACTION_STD = 0.02  # an actor whose actions vary less than this over a batch acts the same everywhere


class FreezeDetector:
    """Warns when vehicles stand still after the warm-up for ``patience`` iterations in a row (the TD3 full-brake freeze).

    A TD3-family actor can saturate at full brake: vehicles stop, every braking action gives the
    same next state, the critic is flat there and the return is exactly 0 (docs/guides/train-cig-td3.md, "TD3 freeze").
    ``update`` takes :func:`iteration_metrics` and returns a warning line once the mean speed of
    the acting vehicles has stayed below ``speed_threshold`` m/s for ``patience`` iterations.
    """

    def __init__(self, warmup_steps: int = 0, patience: int = 3, speed_threshold: float = 0.5):
        self.warmup_steps, self.patience, self.speed_threshold = warmup_steps, patience, speed_threshold
        self.still = 0

    def update(self, metrics: dict[str, float]) -> str | None:
        """The warning for this iteration, or None."""
        speed = metrics.get("mean_speed", float("nan"))
        if metrics["env_steps"] <= self.warmup_steps or math.isnan(speed):
            return None
        self.still = self.still + 1 if speed < self.speed_threshold else 0
        if self.still < self.patience:
            return None
        saturation = metrics.get("learner/actor_saturation", float("nan"))
        spread = metrics.get("learner/actor_action_std", float("nan"))
        head = f"warning: vehicles have stood still (mean speed {speed:.2f} m/s < {self.speed_threshold}) for {self.still} iterations; "
        if spread < COLLAPSED_ACTION_STD and not saturation >= 0.5:  # a saturated freeze also has ~0 spread: the guard advice
            return head + (
                f"the actor gives one action whatever it observes (action std over the batch {spread:.3f}, saturated "
                f"{saturation:.0%}): a collapsed actor, which the saturation guard does not undo (TraCo's domain critic alone did "
                "this: docs/results/journal.md); its critic's action gradient is the suspect"
            )
        return head + (
            f"saturated actor outputs {saturation:.0%}. A TD3 actor frozen at full brake does not recover by itself "
            "(docs/guides/train-cig-td3.md: TD3 freeze): try --set actor_preact_penalty=1e-3 actor_preact_threshold=2"
        )


def outcome_text(metrics: dict[str, float]) -> str:
    """``"  agents 12  success 0.250  collision 0.083  speed 6.1 m/s  saturated 4%"`` from :func:`iteration_metrics` (parts that exist)."""
    text = ""
    if metrics["agents_finished"]:
        n, success, collision = int(metrics["agents_finished"]), metrics["train_success_rate"], metrics["train_collision_rate"]
        text += f"  agents {n}  success {success:.3f}  collision {collision:.3f}"
    if not math.isnan(metrics.get("mean_speed", float("nan"))):
        text += f"  speed {metrics['mean_speed']:.1f} m/s"
    if "learner/actor_saturation" in metrics:
        text += f"  saturated {metrics['learner/actor_saturation']:.0%}"
    return text


def checkpoint_meta(name: str, scenario: str, seed: int, overrides: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """The coin_app metadata stored with every checkpoint (what evaluation and export read back)."""
    env_cfg, _ = registry.split_overrides(name, overrides, scenario)
    learners = {k: v for k, v in overrides.items() if k in registry.LEARNER_KEYS}  # how it trained, not what a CPU machine rebuilds
    rebuilt = {k: v for k, v in overrides.items() if k not in learners}
    meta = {"algo": name, "scenario": scenario, "seed": seed, "overrides": rebuilt, "env_config": env_cfg}
    return meta | ({"learners": learners} if learners else {}) | extra


STOPPED_AT_BUDGET, STOPPED_AT_MAX_MINUTES = "steps", "max_minutes"  # summary["stopped"], or the name of the signal


class StopRequest:
    """Set by SIGTERM or SIGINT while :func:`stop_on_signal` is active: the run stops after its current iteration."""

    def __init__(self) -> None:
        self.signal: str | None = None  # the name of the first signal received


@contextmanager
def stop_on_signal() -> Iterator[StopRequest]:
    """While inside (main thread), the first SIGTERM or SIGINT asks for a stop after the current iteration; a second one stops at once."""
    request = StopRequest()

    def handler(signum: int, frame: Any) -> None:  # sets the flag only: printing here could re-enter a write to stdout
        name = signal.Signals(signum).name
        if request.signal is not None:
            raise KeyboardInterrupt(f"second {name}: stopping at once (the last checkpoint is kept)")
        request.signal = name

    if threading.current_thread() is not threading.main_thread():  # handlers can only be set there; signals keep their default
        yield request
        return
    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield request
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def save(algo: Algorithm, checkpoint: Path, meta: dict[str, Any], atomic: bool = True) -> None:
    """Save the algorithm, its coin_app metadata and manifest to ``checkpoint`` (atomically: ``checkpoint_files.save_checkpoint``)."""
    save_checkpoint(algo, checkpoint, meta, atomic=atomic)


def check_resume(checkpoint: Path, meta: dict[str, Any], name: str, scenario: str, overrides: dict[str, Any]) -> None:
    """Refuse to resume ``checkpoint`` (metadata ``meta``) as another algorithm, scenario, scenario config or network shape."""
    if meta.get("algo") != name:
        raise ValueError(f"--resume {checkpoint} was trained by {meta.get('algo')!r}, not {name!r}; allowed: --algo {meta.get('algo')}")
    if meta.get("scenario") != scenario:
        trained = meta.get("scenario")
        raise ValueError(f"--resume {checkpoint} was trained on scenario {trained!r}, not {scenario!r}; allowed: --scenario {trained}")
    spec = registry.get(name)
    old_overrides = dict(meta.get("overrides", {}))
    old_env, old_algo = registry.split_overrides(name, old_overrides, scenario)
    new_env, _ = registry.split_overrides(name, overrides, scenario)
    old_cfg = config_from_dict(scenario, {**spec.scenario_defaults(old_algo), **old_env})
    new_cfg = config_from_dict(scenario, {**spec.scenario_defaults(dict(overrides)), **new_env})
    if old_cfg != new_cfg:
        diff = sorted(k for k in old_cfg.__dataclass_fields__ if getattr(old_cfg, k) != getattr(new_cfg, k))
        shown = ", ".join(f"{k}={getattr(old_cfg, k)!r} there, {getattr(new_cfg, k)!r} here" for k in diff[:4])
        raise ValueError(
            f"--resume {checkpoint} was trained on another {scenario} config ({shown}); allowed: the checkpoint's --set values"
        )
    seed = int(meta.get("seed", 0))
    old_shapes = _parameter_shapes(fresh_module(name, scenario, old_overrides, seed))
    new_shapes = _parameter_shapes(fresh_module(name, scenario, dict(overrides), seed))
    if old_shapes != new_shapes:
        diff = sorted(k for k in old_shapes.keys() | new_shapes.keys() if old_shapes.get(k) != new_shapes.get(k))
        k = diff[0]
        raise ValueError(
            f"--resume {checkpoint} has another network shape ({k}: {old_shapes.get(k)} there, {new_shapes.get(k)} here; "
            f"{len(diff)} parameter(s) differ); allowed: the checkpoint's --set values {old_overrides}"
        )


def _parameter_shapes(module: RLModule) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every parameter and buffer of a module."""
    return {k: tuple(v.shape) for k, v in module.state_dict().items() if hasattr(v, "shape")}


def check_run_dir(out: Path, resume: Path | None, overwrite: bool) -> None:
    """Refuse ``out`` if it holds an earlier run (unless resumed or overwritten) or cannot be written; before any work."""
    earlier = [p for p in (out / "checkpoint", out / ("checkpoint" + PREVIOUS_SUFFIX), out / "summary.json") if p.exists()]
    if earlier and resume is None and not overwrite:
        raise ValueError(
            f"{out} holds an earlier run ({earlier[0].name}); allowed: --resume {out / 'checkpoint'} to continue it, "
            "--overwrite to replace it, or another --out"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".coin_app_write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"cannot write the run directory {out}: {exc.strerror or exc}; allowed: a writable path for --out") from exc


def _eval_line(metrics: dict[str, float]) -> str:
    """The log line of a periodic evaluation."""
    shown = ("success_rate", "collision_rate", "out_of_road_rate")
    return "      eval (validation seeds): " + "  ".join(f"{k} {metrics.get(k, float('nan')):.3f}" for k in shown)


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
) -> dict[str, Any]:
    """Train for ``steps`` env steps or ``max_minutes`` of wall time; checkpoints every ``checkpoint_every`` iterations and at the end.

    ``threads``: torch threads of this process (its learner and local env runner; one by default,
    as every Ray worker gets). ``address``: a running Ray cluster to use instead of a local session
    over all of this machine's cores. ``out`` must not hold an earlier run unless ``resume`` or
    ``overwrite``; ``resume`` must be a complete checkpoint (or its ``.prev``, after an interrupted
    save) of the same algorithm, scenario config and network shape. Everything is checked before
    any work starts. ``progress``: the progress bar (``None``: on a terminal only; see ``RunProgress``).
    """
    if steps < 1:
        raise ValueError(f"bad steps {steps}; allowed: an integer >= 1")
    if max_minutes is not None and not max_minutes > 0:
        raise ValueError(f"bad max_minutes {max_minutes}; allowed: a number > 0 or None")
    if checkpoint_every < 1:
        raise ValueError(f"bad checkpoint_every {checkpoint_every}; allowed: an integer >= 1")
    if not (isinstance(threads, int) and threads >= 1):
        raise ValueError(f"bad threads {threads!r}; allowed: an integer >= 1")
    cfg = build_config(name, scenario, overrides, seed)
    if resume is not None:
        found, resume_meta = latest_complete(resume)
        if found != resume:
            log(f"{resume} is incomplete (a save was interrupted); resuming from the previous checkpoint {found}")
        resume = found
        check_resume(resume, resume_meta, name, scenario, overrides)
    check_run_dir(out, resume, overwrite)
    spec = registry.get(name)
    warmup = cfg.warmup_steps if "warmup_steps" in spec.hyperparameters else 0
    if warmup and steps <= warmup:
        log(
            f"warning: --steps {steps} <= warmup_steps {warmup}: every action is uniform random and the networks are never "
            f"updated (losses print nan). Train longer, or --set warmup_steps=N; small settings that learn in minutes: --quick"
        )
    torch.set_num_threads(threads)
    if not ray.is_initialized():
        ray.init(address=address or "local", include_dashboard=False, log_to_driver=False, configure_logging=False)
        where = f"the cluster at {address}" if address else "a local session (all of this machine's cores)"
        log(f"ray: {where} with {int(ray.cluster_resources().get('CPU', 0))} CPUs, {int(ray.cluster_resources().get('GPU', 0))} GPUs")
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
        (out / "config.json").write_text(json.dumps(meta, indent=2, default=str))
        if spec.capabilities.joint_replay:
            agents = scenario_config_of(cfg).num_agents
            log(f"replay: {cfg.replay_capacity:,} agent transitions, about {cfg.replay_capacity // agents:,} env steps at {agents} agents")
        freeze = FreezeDetector(warmup)
        board = SummaryWriter(str(out / TENSORBOARD_DIR))  # what Tune trials write too: tensorboard --logdir <out>
        t0 = time.perf_counter()
        start = sampled = int(algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0))
        result: dict[str, Any] = {}
        last_eval: dict[str, float] = {}
        ckpt = out / "checkpoint"
        bar = RunProgress(steps, start, log, progress)
        if isinstance(algo, ProgressReporting):  # long iterations: their updates are shown as they go
            algo.progress_callback = bar.phase
        stopped = STOPPED_AT_BUDGET  # why the loop ended: the budget, max_minutes or a signal's name
        saved = None  # env steps of the newest checkpoint written by this run

        def save_at(env_steps: int) -> int:
            bar.phase("saving checkpoint", 0, 0)
            save(algo, ckpt, meta | {"env_steps": int(env_steps)})
            return env_steps

        try:
            with stop_on_signal() as stop:
                while sampled < steps and stop.signal is None:
                    if max_minutes is not None and time.perf_counter() - t0 >= 60.0 * max_minutes:
                        stopped = STOPPED_AT_MAX_MINUTES
                        break
                    result = algo.train()
                    m = iteration_metrics(result)
                    sampled = m["env_steps"]
                    bar.advance(sampled)
                    it = int(result["training_iteration"])
                    elapsed = time.perf_counter() - t0
                    critic = next((m[k] for k in CRITIC_LOSS_KEYS if k in m), np.nan)
                    bar.say(
                        f"iter {it:>4}  env steps {sampled:>8}  {(sampled - start) / max(elapsed, 1e-9):7.1f} steps/s  "
                        f"episode return {m['episode_return_mean']:8.2f}  critic loss {critic:8.4f}" + outcome_text(m)
                    )
                    for key, value in m.items():
                        if math.isfinite(value):
                            board.add_scalar(key, value, global_step=sampled)
                    board.flush()
                    warning = freeze.update(m)
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
        "eval": last_eval,
        "stopped": stopped,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
