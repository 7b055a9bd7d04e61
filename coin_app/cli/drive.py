"""``demo`` and ``policies``: drive a scenario with a shipped policy, a file or the heuristic driver (no Ray, no torch)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from coin_app.adapters.lcf import with_lcf
from coin_app.cli.flags import overrides_of
from coin_app.cli.output import CONSOLE_ROWS, format_metrics, shown
from coin_app.cli.policy_settings import driving_config
from coin_app.evaluation.evaluate import record
from coin_app.evaluation.fit import policy_fit
from coin_app.evaluation.metrics import EpisodeRecorder
from coin_app.evaluation.outputs import write_text_atomic
from coin_app.inference import load_policy, shipped_policies
from coin_app.inference.shipped import is_shipped_name
from coin_app.sim import schema
from coin_app.sim.config import ScenarioConfig, make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.heuristic import HeuristicDriver
from coin_app.sim.rendering import EpisodeTrace, plot_trajectories, render_frame, write_gif
from coin_app.sim.replay import write_replay
from coin_app.sim.rollout import DictEnvs, rollout
from coin_app.sim.scenes import ARENA

HEURISTIC = "heuristic"
AUTO = "auto"


@dataclass
class Drive:
    """One policy's run of the demo episode: its label, what it recorded and its GIF frames."""

    label: str
    env: DrivingEnv
    recorder: EpisodeRecorder
    trace: EpisodeTrace = field(default_factory=EpisodeTrace)
    frames: list[np.ndarray] = field(default_factory=list)
    steps: int = 0


def default_policy(scenario: str | None) -> str:
    """The shipped policy trained on ``scenario`` (default: the first driving one), else the heuristic driver."""
    for name, rec in shipped_policies().items():
        if rec["scenario"] != "arena" and (scenario is None or rec["scenario"] == scenario):
            return name
    return HEURISTIC


def demo_config(source: str, scenario: str | None, preset: str | None, overrides: dict[str, Any]) -> ScenarioConfig:
    """The config ``source`` drives on: a learned policy's training config (its vehicle count too) under ``overrides``;
    the heuristic driver: the scenario's defaults (intersection unless given)."""
    if source == HEURISTIC:
        return make_config(scenario or "intersection", preset or "paper", **overrides)
    return driving_config(load_policy(source).meta, source, scenario, overrides, preset)  # refuses an arena policy


def fitted_policy(source: str, config: ScenarioConfig) -> tuple[Any, list[str]]:
    """``source`` (a shipped name or an exported file) loaded as evaluation runs it (a CoPO actor with its per-vehicle
    LCF draws), and the warnings of driving it on ``config``; a ValueError in one line, before any work, if it cannot
    drive there: an arena policy, another observation layout (``policy_fit``), or not ``ACT_DIM`` action numbers."""
    policy = load_policy(source)
    meta = getattr(policy, "meta", {})
    if meta.get("scenario") == ARENA:
        raise ValueError(f"{source} is an arena policy; allowed: a driving policy (arena policies: python -m coin_app evaluate-arena)")
    obs_dim = getattr(policy, "obs_dim", config.obs_dim)  # its own input: the env's observation (and a CoPO actor's LCF)
    warnings = policy_fit(meta, config, source, obs_dim)
    actions = np.shape(policy(np.full((1, obs_dim), 0.5, np.float32)))  # a mid-range input (observations lie in [0, 1])
    if actions != (1, schema.ACT_DIM):
        raise ValueError(
            f"{source} gives actions of shape {actions} for one vehicle; {config.scenario} takes (1, {schema.ACT_DIM}) "
            "(steering, throttle); allowed: a driving policy"
        )
    return with_lcf(policy), warnings


def drive(policy: Any, label: str, config: ScenarioConfig, seed: int, steps: int, gif_every: int | None, log: bool) -> Drive:
    """Run ``policy`` (``heuristic``, a shipped name, a file, or a batch policy object) for one episode of ``config`` from
    ``seed``, recording its metrics, its trace and (every ``gif_every`` steps) its frames."""
    env = DrivingEnv(config)
    if isinstance(policy, str):
        source = policy
        policy = HeuristicDriver(env) if source == HEURISTIC else load_policy(source)
        if source != HEURISTIC and policy.obs_dim != config.obs_dim:
            raise ValueError(f"{source} takes {policy.obs_dim} observation numbers; {config.scenario} gives {config.obs_dim}")
    run = Drive(label, env, EpisodeRecorder(config.max_agent_steps))
    t0, agent_steps = time.perf_counter(), 0
    for step in rollout(DictEnvs([env]), policy, [seed], steps):
        result = step.results[0]
        record(step, [run.recorder])
        run.trace.record(env, result.infos)
        agent_steps += len(result.rewards)
        run.steps = step.t
        if gif_every and step.t % gif_every == 0:  # t = 0: the reset frame
            run.frames.append(render_frame(env))
        if log and step.t > 0 and (step.t % 50 == 0 or env.episode_over):
            m = run.recorder.metrics()
            print(
                f"  {label:<22} step {step.t:>5}  active {len(env.agents):>3}  vehicles {m['num_vehicles']:>4}  "
                f"arrived {m['num_arrived']:>3}  crashed {m['num_crashed']:>3}  off-road {m['num_out_of_road']:>3}  "
                f"{agent_steps / (time.perf_counter() - t0):,.0f} agent-steps/s",
                flush=True,
            )
    return run


def labelled(frame: np.ndarray, label: str) -> np.ndarray:
    """``frame`` with ``label`` written in its bottom-left corner."""
    image = Image.fromarray(frame)
    ImageDraw.Draw(image).text((8, frame.shape[0] - 18), label, fill=(0, 0, 0))
    return np.asarray(image)


def side_by_side(columns: list[list[np.ndarray]], labels: list[str]) -> list[np.ndarray]:
    """Frames of several runs placed left to right, each labelled (a run that ended early holds its last frame)."""
    n = max(len(c) for c in columns)
    return [np.concatenate([labelled(c[min(k, len(c) - 1)], lab) for c, lab in zip(columns, labels)], axis=1) for k in range(n)]


def metric_table(runs: list[Drive]) -> str:
    """The six COIN metrics, the arrivals' travel steps and the vehicle counts of each run, one column per run."""
    metrics = [r.recorder.metrics() for r in runs]
    head = f"  {'':<18}" + "".join(f"{r.label:>24}" for r in runs)
    rows = [f"  {label:<18}" + "".join(f"{shown(m.get(key, float('nan')), fmt):>24}" for m in metrics) for key, label, fmt in CONSOLE_ROWS]
    return "\n".join([head, *rows])


def cmd_demo(args: argparse.Namespace) -> int:
    """Drive a scenario with a trained policy (default: the shipped CIG-TD3) beside the heuristic driver; print both metric
    rows; write a GIF (one panel per policy), a trajectory plot, the metrics and a replay page per policy."""

    if args.steps < 1:
        raise ValueError(f"bad --steps {args.steps}; allowed: an integer >= 1")
    if args.gif_every < 1:
        raise ValueError(f"bad --gif-every {args.gif_every}; allowed: an integer >= 1")
    overrides = overrides_of(args.set, {"num_agents": ("--num-agents", args.num_agents)})
    source = default_policy(args.scenario) if args.policy == AUTO else args.policy
    compare = None if args.compare in ("none", source) else args.compare
    for s in (source, compare):
        if s is not None and s != HEURISTIC and not is_shipped_name(s) and not Path(s).is_file():
            names = ", ".join(shipped_policies())
            raise ValueError(f"bad policy {s!r}; allowed: {HEURISTIC}, a shipped policy ({names}) or an exported policy file")
    config = demo_config(source, args.scenario, args.preset, overrides)
    if config.backend != "native":
        raise ValueError(
            f"demo drives the native simulator, not backend {config.backend!r} (from --set or the policy's training config); "
            f"allowed: backend native, or python -m coin_app evaluate POLICY --backend {config.backend}"
        )
    sources = [source] + ([compare] if compare else [])
    loaded, warnings = {}, []
    for s in sources:  # every learned policy checked against the episode's env before anything is written
        if s != HEURISTIC:
            loaded[s], fit = fitted_policy(s, config)
            warnings += fit
    for line in warnings:
        print(line, file=sys.stderr)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"demo: {config.scenario}, {config.num_agents} vehicles at reset, seed {args.seed}, up to {args.steps} steps -> {out}")
    print(
        f"  driving: {' | '.join(sources)}"
        + (" (--compare heuristic puts the heuristic driver beside it)" if args.compare == "none" else "")
    )
    t0 = time.perf_counter()
    gif_every = None if args.no_gif else args.gif_every
    runs = [drive(loaded.get(s, s), s, config, args.seed, args.steps, gif_every, log=True) for s in sources]
    title = f"{config.scenario}, {config.num_agents} vehicles, seed {args.seed}"
    traj = plot_trajectories(runs[0].trace, runs[0].env.sim.map, out / "trajectories.png", title=f"{title}: {runs[0].label}")
    gif = (
        None
        if args.no_gif
        else write_gif(side_by_side([r.frames for r in runs], [r.label for r in runs]), out / "episode.gif", fps=10 / args.gif_every)
    )
    pages = (
        [
            write_replay(
                r.trace, r.env.sim.map, out / f"replay{'' if k == 0 else '-' + Path(r.label).stem}.html", title=f"{title}: {r.label}"
            )
            for k, r in enumerate(runs)
        ]
        if args.html
        else []
    )
    metrics = {r.label: r.recorder.metrics() for r in runs}
    write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=2, default=float))
    print(f"\nsummary: {max(r.steps for r in runs)} env steps per policy, {time.perf_counter() - t0:.1f} s")
    print(metric_table(runs) if compare else format_metrics(metrics[source]))
    print(f"  trajectory plot: {traj}")
    if gif is not None:
        print(f"  animation:       {gif}" + (f" (left: {source}, right: {compare})" if compare else ""))
    for page, run in zip(pages, runs):
        print(f"  replay page:     {page} ({run.label}; open it in a browser)")
    print(f"  metrics:         {out / 'metrics.json'}")
    for line in warnings:  # in the summary too, beside the figures
        print(f"  {line}")
    return 0


def cmd_policies(args: argparse.Namespace) -> int:
    """List the shipped policies: name, what they are, what they were trained on and their test figures."""
    for name, rec in shipped_policies().items():
        test = ", ".join(f"{k} {v}" for k, v in rec["test"].items() if isinstance(v, (int, float)))
        print(f"{name}\n  {rec['description']}\n  {rec['algo']} on {rec['scenario']} ({rec['num_agents']}), {rec['protocol']}")
        print(f"  test: {test} ({rec['test'].get('episodes', '')}); commit {rec['commit']}")
    print("\nload one without Ray or torch: coin_app.inference.load_policy(NAME); drive one: python -m coin_app demo --policy NAME")
    return 0
