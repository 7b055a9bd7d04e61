"""What a run shows and measures while it trains: the progress bar, iteration metrics, periodic evaluation, the freeze guard."""

from __future__ import annotations

import logging
import math
import time
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.callbacks.callbacks import RLlibCallback
from tqdm import tqdm

from coin_app.algorithms.checkpoints import actor_policy
from coin_app.algorithms.common import SHARED_MODULE_ID, scenario_config_of
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.metrics import aggregate
from coin_app.sim.seeds import validation_seeds

EVAL_RESULT_KEY = "coin_eval"  # the periodic evaluation's metrics in an iteration's result


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


def _learner_policy(learner: Any) -> Any:
    """The evaluation policy of a learner's shared module (CoPO: LCFs as the module's ``evaluation_lcf`` says)."""
    return actor_policy(learner.module[SHARED_MODULE_ID].unwrapped())


def evaluate_algorithm(algo: Algorithm, seeds: list[int]) -> dict[str, float]:
    """Mean metrics of an algorithm's current deterministic actor (the learner's) on ``seeds`` (either backend)."""
    policy = next(iter(algo.learner_group.foreach_learner(_learner_policy))).get()
    per_episode = evaluate_policy(policy, scenario_config_of(algo.config), seeds)
    return {k: v["mean"] for k, v in aggregate(per_episode).items()}


class PeriodicEvaluation(RLlibCallback):
    """Every ``eval_every`` iterations, the deterministic actor on ``eval_episodes`` validation seeds (``result["coin_eval"]``,
    with ``cpu_s``: this process's CPU seconds the evaluation took)."""

    def on_train_result(self, *, algorithm: Algorithm, result: dict, **kwargs: Any) -> None:
        """Add the periodic evaluation to this iteration's result when it is due."""
        every = algorithm.config.eval_every
        if every and result["training_iteration"] % every == 0:
            result[EVAL_RESULT_KEY] = validation_metrics(algorithm)


def validation_metrics(algorithm: Algorithm) -> dict[str, float]:
    """The periodic evaluation now: the deterministic actor on the config's ``eval_episodes`` validation seeds, with the
    ``cpu_s`` of this process it took."""
    start = time.process_time()
    metrics = evaluate_algorithm(algorithm, validation_seeds(algorithm.config.eval_episodes))
    return metrics | {"cpu_s": time.process_time() - start}


def process_tree_cpu_seconds(pid: int | None = None) -> float:
    """CPU seconds (user + system) used so far by process ``pid`` (default: this one) and every process it started.

    Live processes count their own time; ended ones count once their parent has reaped them (in that parent's children
    times), as ``time`` counts a command. A local Ray session's GCS, raylet and workers are this process's descendants.
    """
    import psutil  # optional: after ray (imported above), Ray's packaged copy (ray/thirdparty_files); no dependency of its own

    root = psutil.Process(pid)
    total = 0.0
    for proc in [root, *root.children(recursive=True)]:
        try:
            t = proc.cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):  # ended (its time is its parent's) or not ours
            continue
        total += t.user + t.system + t.children_user + t.children_system
    return total


def iteration_metrics(result: dict[str, Any]) -> dict[str, float]:
    """The flat per-iteration figures coin_app logs and reports to Tune, from an RLlib ``algo.train()`` result.

    ``env_steps``, ``episode_return_mean``, ``episode_len_mean``, the agent outcomes of the
    iteration (``agents_finished``, ``train_success_rate``, ``train_collision_rate``; NaN when
    no agent ended), the acting vehicles' ``mean_speed`` (m/s; NaN without driving agents),
    every scalar learner metric of the shared module (``learner/<name>``) and
    the last periodic evaluation on validation seeds (``eval/<metric>``), if any.
    The train loop adds the run's clocks (``cpu_s``, ``wall_s``: see ``loop.RunClock``).
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


def _eval_line(metrics: dict[str, float]) -> str:
    """The log line of a periodic evaluation."""
    shown = ("success_rate", "collision_rate", "out_of_road_rate")
    return "      eval (validation seeds): " + "  ".join(f"{k} {metrics.get(k, float('nan')):.3f}" for k in shown)
