"""Seconds per IPPO learner update in fp32 and in bf16 (``--set precision=bf16``), side by side on the same episodes.

Usage: python benchmarks/ppo_update.py [--scenario intersection] [--repeats 3] [--rllib-step] [--set KEY=VALUE ...]

Builds IPPO at its reference settings (1600 env steps per batch, 5 epochs, minibatches of 512
agent transitions, two 256-wide tanh layers per network; ``--set`` overrides them as the CLI's
``--set`` does), samples one train batch once with the config's batched env runner, then builds an
fp32 and a bf16 learner from the same seed and times ``learner.update`` on copies of the same
episodes (the learner connector edits episodes in place): one warm-up update each, then
``--repeats`` rounds alternating the two. Prints the median seconds per update (learner connector
+ all minibatch steps), the part spent in the minibatch steps, their ratio, and each learner's
last losses as a sanity check. ``--rllib-step`` also times, in turn with the others, the fp32
learner with RLlib's own gradient step (PyTorch's per-tensor Adam, two finiteness checks per
gradient tensor) in place of this project's (fused Adam, one check: ``gradient_step.py``), and
prints the ratio. Runs on one torch thread (OMP_NUM_THREADS=1 unless set).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import time
import types
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import torch  # noqa: E402
from ray.rllib.core.learner.torch.torch_learner import TorchLearner  # noqa: E402
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME  # noqa: E402

from coin_app.adapters.batched_runner import BatchedEnvRunner  # noqa: E402
from coin_app.algorithms.common import SHARED_MODULE_ID  # noqa: E402
from coin_app.training import build_config  # noqa: E402

PRECISIONS = ("fp32", "bf16")
RLLIB_STEP = "fp32, RLlib's gradient step"  # the label of the --rllib-step comparison


def parse_set(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings as a dict, each value read as JSON when it parses (numbers, booleans), else as a string."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"bad --set item {item!r}; allowed: KEY=VALUE")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


class TimedLearner:
    """A learner built from ``cfg`` with the seconds of its minibatch steps recorded per update."""

    def __init__(self, cfg: Any, spaces: dict[str, Any], seed: int):
        torch.manual_seed(seed)
        self.cfg, self.learner = cfg, cfg.build_learner(spaces=spaces)
        self.step_seconds = 0.0
        self.steps = 0
        step = self.learner._possibly_compiled_update

        def timed(batch: dict[str, Any], **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return step(batch, **kwargs)
            finally:
                self.step_seconds += time.perf_counter() - t0
                self.steps += 1

        self.learner._possibly_compiled_update = timed

    def use_rllibs_gradient_step(self) -> None:
        """Step as RLlib 2.60's ``TorchLearner`` does: its ``apply_gradients`` and PyTorch's per-tensor Adam."""
        self.learner.apply_gradients = types.MethodType(TorchLearner.apply_gradients, self.learner)
        for optimizer in self.learner._named_optimizers.values():
            for group in optimizer.param_groups:
                group["fused"], group["foreach"] = None, False

    def update(self, episodes: list[Any]) -> tuple[float, float, dict[str, Any]]:
        """(seconds of one update on a copy of ``episodes``, seconds of its minibatch steps, its results)."""
        episodes = copy.deepcopy(episodes)
        steps = sum(len(e) for e in episodes)
        self.step_seconds, self.steps = 0.0, 0
        t0 = time.perf_counter()
        results = self.learner.update(
            episodes=episodes,
            timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: steps},
            num_epochs=self.cfg.num_epochs,
            minibatch_size=self.cfg.minibatch_size,
        )
        return time.perf_counter() - t0, self.step_seconds, results


def scalar(value: Any) -> float:
    """A logged metric as a float."""
    value = value.peek() if hasattr(value, "peek") else value
    return float(value)


def main() -> None:
    """Sample once, then time fp32 and bf16 updates side by side."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="intersection")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    parser.add_argument("--rllib-step", action="store_true", help="also time fp32 with RLlib's own gradient step, side by side")
    args = parser.parse_args()
    torch.set_num_threads(1)
    overrides = parse_set(args.set)
    if "precision" in overrides:
        raise SystemExit("bad --set key 'precision'; the benchmark runs both 'fp32' and 'bf16'")
    configs = {p: build_config("ippo", args.scenario, {**overrides, "precision": p}, args.seed) for p in PRECISIONS}
    cfg = configs["fp32"]
    runner = BatchedEnvRunner(config=cfg, worker_index=0)
    t0 = time.perf_counter()
    episodes = runner.sample()
    sample_s = time.perf_counter() - t0
    spaces = {SHARED_MODULE_ID: runner.get_spaces()[SHARED_MODULE_ID]}
    runner.stop()
    env_steps = sum(e.env_steps() for e in episodes)
    rows = sum(e.agent_steps() for e in episodes)
    print(
        f"IPPO {args.scenario}: {env_steps} env steps, {rows} agent rows (sampled in {sample_s:.1f} s); "
        f"{cfg.num_epochs} epochs, minibatch {cfg.minibatch_size}, hidden {cfg.model_config['fcnet_hiddens']}, "
        f"torch threads {torch.get_num_threads()}"
    )
    learners = {p: TimedLearner(c, spaces, args.seed) for p, c in configs.items()}
    if args.rllib_step:
        learners[RLLIB_STEP] = TimedLearner(cfg, spaces, args.seed)
        learners[RLLIB_STEP].use_rllibs_gradient_step()
    for timed in learners.values():  # warm-up
        timed.update(episodes)
    seconds: dict[str, list[float]] = {p: [] for p in learners}
    step_seconds: dict[str, list[float]] = {p: [] for p in learners}
    last: dict[str, dict[str, Any]] = {}
    for _ in range(args.repeats):
        for p, timed in learners.items():
            total, steps, results = timed.update(episodes)
            seconds[p].append(total)
            step_seconds[p].append(steps)
            last[p] = results[SHARED_MODULE_ID]
    for p in learners:
        total, steps = statistics.median(seconds[p]), statistics.median(step_seconds[p])
        losses = ", ".join(f"{k} {scalar(last[p][k]):.4g}" for k in ("policy_loss", "vf_loss", "mean_kl_loss", "entropy"))
        print(
            f"{p}: {total:.2f} s per update ({steps:.2f} s in {learners[p].steps} minibatch steps, "
            f"{1e3 * steps / learners[p].steps:.1f} ms each); runs {', '.join(f'{s:.2f}' for s in seconds[p])}; last: {losses}"
        )
    fp32, bf16 = statistics.median(seconds["fp32"]), statistics.median(seconds["bf16"])
    fp32_steps, bf16_steps = statistics.median(step_seconds["fp32"]), statistics.median(step_seconds["bf16"])
    print(f"fp32 / bf16: {fp32 / bf16:.2f}x per update, {fp32_steps / bf16_steps:.2f}x in the minibatch steps")
    if args.rllib_step:
        theirs, their_steps = statistics.median(seconds[RLLIB_STEP]), statistics.median(step_seconds[RLLIB_STEP])
        ratio, step_ratio = fp32 / theirs, fp32_steps / their_steps
        print(f"fp32, this learner's gradient step / RLlib's: {ratio:.2f} per update, {step_ratio:.2f} in the minibatch steps")


if __name__ == "__main__":
    main()
