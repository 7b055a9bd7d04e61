"""Command line: ``python -m coin_app <command> ...`` (``--help`` on any command)."""

from __future__ import annotations

import argparse
import json
import math
import pickle
import shlex
import sys
import time
import traceback
import zipfile
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cluster import jobs
from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import read_metadata
from coin_app.algorithms.checkpoints import export_actor, load_module
from coin_app.algorithms.registry import parse_overrides, quick_settings
from coin_app.evaluation.arena_report import PAGE as ARENA_PAGE
from coin_app.evaluation.arena_report import is_arena_eval, load_arena_eval, policy_labels, write_arena_html, write_side_by_side
from coin_app.evaluation.arena_suite import (
    PROTOCOLS,
    evaluate_suite,
    load_arena_policy,
    markdown_table,
    parse_cases,
    plot_scenarios,
    policy_config,
    summarize,
)
from coin_app.evaluation.critic_probe import probe_checkpoint
from coin_app.evaluation.evaluate import evaluate_policy, record
from coin_app.evaluation.metrics import METRIC_KEYS, EpisodeRecorder, aggregate
from coin_app.evaluation.policies import as_policy
from coin_app.evaluation.report import ReportOptions, build_report
from coin_app.inference import export_policy, load_policy
from coin_app.inference.formats import check_format
from coin_app.inference.switching import write_pair
from coin_app.sim.arena.config import GENERATORS, ArenaConfig
from coin_app.sim.config import DEFAULT_NUM_AGENTS, PRESETS, DynamicsConfig, ScenarioConfig, make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.heuristic import HeuristicDriver
from coin_app.sim.rendering import EpisodeTrace, plot_trajectories, render_frame, write_gif
from coin_app.sim.rollout import DictEnvs, rollout
from coin_app.sim.scenarios import config_from_dict
from coin_app.sim.seeds import TEST_SEED_BASE, eval_test_seeds
from coin_app.training import STOPPED_AT_BUDGET, train
from tuning.sweep import run_sweep, write_generalization

CONSOLE_FORMATS = {"efficiency": "{:.0f}", "safety": "{:.0f}", "avg_travel_steps": "{:.1f}"}  # the rates: "{:.3f}"
# (key, label, format) of the six COIN metrics as the commands print them
METRIC_ROWS = tuple((k, k.replace("_", " ").replace("out of road", "off-road"), CONSOLE_FORMATS.get(k, "{:.3f}")) for k in METRIC_KEYS)
# ... then the arrivals-only travel steps and the vehicle counts ("count": an integer, or one decimal for a mean)
CONSOLE_ROWS = (
    *METRIC_ROWS,
    ("avg_travel_steps_arrived", "travel (arrived)", "{:.1f}"),
    ("num_vehicles", "vehicles", "count"),
    ("num_timeout", "time-outs", "count"),
)
PRESET_KEYS = tuple(dict.fromkeys(k for values in PRESETS.values() for k in values))  # the config keys some preset sets


def shown(value: float, fmt: str) -> str:
    """``value`` as the console shows it: ``fmt`` (``"count"``: no decimals if whole, else one); ``n/a`` for NaN."""
    if isinstance(value, float) and math.isnan(value):
        return "n/a"
    if fmt == "count":
        return f"{value:.0f}" if float(value).is_integer() else f"{value:.1f}"
    return fmt.format(value)


def format_metrics(metrics: dict[str, float]) -> str:
    """The six COIN metrics, the arrivals' travel steps, vehicles and time-outs as an aligned two-column table."""
    return "\n".join(f"  {label:<18}{shown(metrics.get(key, math.nan), fmt):>10}" for key, label, fmt in CONSOLE_ROWS)


def cmd_demo(args: argparse.Namespace) -> int:
    """Run the heuristic driver on a scenario; print the metrics and write a GIF and a trajectory plot."""

    overrides = parse_overrides(args.set)
    if args.num_agents is not None:
        overrides["num_agents"] = args.num_agents
    if args.steps < 1:
        raise ValueError(f"bad --steps {args.steps}; allowed: an integer >= 1")
    if args.gif_every < 1:
        raise ValueError(f"bad --gif-every {args.gif_every}; allowed: an integer >= 1")
    config = make_config(args.scenario, args.preset, **overrides)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env = DrivingEnv(config)
    recorder, trace, frames = EpisodeRecorder(config.max_agent_steps), EpisodeTrace(), []
    print(f"demo: {config.scenario}, {config.num_agents} agents, seed {args.seed}, up to {args.steps} steps -> {out}")
    t0 = time.perf_counter()
    agent_steps = 0
    for step in rollout(DictEnvs([env]), HeuristicDriver(env), [args.seed], args.steps):
        result = step.results[0]
        record(step, [recorder])
        trace.record(env, result.infos)
        agent_steps += len(result.rewards)  # one reward per agent that acted
        if not args.no_gif and step.t % args.gif_every == 0:  # t = 0: the reset frame
            frames.append(render_frame(env))
        if step.t > 0 and (step.t % 50 == 0 or env.episode_over):
            m = recorder.metrics()
            print(
                f"  step {step.t:>5}  active {len(env.agents):>3}  vehicles {m['num_vehicles']:>4}  "
                f"arrived {m['num_arrived']:>3}  crashed {m['num_crashed']:>3}  off-road {m['num_out_of_road']:>3}  "
                f"{agent_steps / (time.perf_counter() - t0):,.0f} agent-steps/s",
                flush=True,
            )
    metrics = recorder.metrics()
    traj = plot_trajectories(trace, env.sim.map, out / "trajectories.png", title=f"{config.scenario}: heuristic driver, seed {args.seed}")
    gif = None if args.no_gif else write_gif(frames, out / "episode.gif", fps=10 / args.gif_every)
    (out / "metrics.json").write_text(json.dumps({k: v for k, v in metrics.items()}, indent=2, default=float))
    print(f"\nsummary: {step.t} env steps, {metrics['num_vehicles']} vehicles, {time.perf_counter() - t0:.1f} s")
    print(format_metrics(metrics))
    print(f"  trajectory plot: {traj}")
    if gif is not None:
        print(f"  animation:       {gif}")
    print(f"  metrics:         {out / 'metrics.json'}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    """Train an algorithm of the registry; checkpoints and a summary go to ``--out``."""

    overrides = parse_overrides(args.set)
    if args.quick:  # the small settings that learn within minutes, beneath the user's --set
        overrides = {**quick_settings(args.algo), **overrides}
    if args.num_agents is not None:
        overrides["num_agents"] = args.num_agents
    if args.backend != "native":
        overrides["backend"] = args.backend
    out = Path(args.out or f"runs/{args.algo}_{args.scenario}_s{args.seed}")
    resume = Path(args.resume) if args.resume else None
    print(f"train: {args.algo} on {args.scenario}, {args.steps} env steps, seed {args.seed} -> {out}")
    if args.quick:
        print(f"  --quick: {', '.join(f'{k}={v}' for k, v in quick_settings(args.algo).items())} (your --set wins)")
    summary = train(
        args.algo,
        args.scenario,
        args.steps,
        args.seed,
        overrides,
        out,
        args.checkpoint_every,
        resume,
        max_minutes=args.max_minutes,
        threads=args.threads,
        address=args.address,
        overwrite=args.overwrite,
        progress={"auto": None, "always": True, "never": False}[args.progress],
    )
    print(f"\nsummary: {summary['env_steps']} env steps in {summary['iterations']} iterations, {summary['wall_s']:.0f} s")
    print(f"  checkpoint: {summary['checkpoint']}")
    if summary.get("stopped", STOPPED_AT_BUDGET) != STOPPED_AT_BUDGET:
        where = f"{summary['env_steps']} of {args.steps} env steps"
        print(f"  stopped early ({summary['stopped']}) at {where}; continue with --resume {summary['checkpoint']}")
    if summary.get("eval"):
        print("  last periodic evaluation (validation seeds):")
        print(format_metrics(summary["eval"]))
    return 0


def check_preset(preset: str | None) -> None:
    """Refuse a preset name that is not one of :data:`PRESETS` (None: no preset asked for)."""
    if preset is not None and preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; allowed: {', '.join(PRESETS)}")


def with_preset(env_config: dict[str, Any], preset: str | None) -> dict[str, Any]:
    """A stored env_config under an explicit ``preset``: its own preset and every key a preset sets dropped (None: as stored)."""
    check_preset(preset)
    if preset is None:
        return dict(env_config)
    return {**{k: v for k, v in env_config.items() if k != "preset" and k not in PRESET_KEYS}, "preset": preset}


def _evaluation_config(source: Path, scenario: str | None, overrides: dict[str, Any], preset: str | None = None) -> Any:
    """The scenario config to evaluate ``source`` on: its training config (checkpoint / export metadata), ``preset``, then overrides."""

    if source.is_dir():
        meta = read_metadata(source)
        if meta.get("scenario") == "arena" or scenario == "arena":
            raise ValueError(f"{source} is an arena policy; evaluate it with: python -m coin_app evaluate-arena {source}")
        config = config_from_dict(meta["scenario"], {**with_preset(meta.get("env_config", {}), preset), **overrides})
        if scenario is not None and scenario != config.scenario:
            raise ValueError(f"--scenario {scenario} contradicts the checkpoint's scenario {config.scenario}")
        return config
    if not source.is_file():
        raise ValueError(f"policy {source} does not exist; allowed: a checkpoint directory or an exported policy file (.npz, .pt, .onnx)")

    meta = load_policy(source).meta
    scenario = scenario or meta.get("scenario")
    if scenario == "arena":
        raise ValueError(f"{source} is an arena policy; evaluate it with: python -m coin_app evaluate-arena {source}")
    if scenario is None:
        raise ValueError(f"{source} does not say which scenario it was trained on; pass --scenario")
    return config_from_dict(scenario, {**with_preset(meta.get("env_config", {}), preset), **overrides})


def _dynamics_name(dynamics: DynamicsConfig) -> str:
    """``raycast`` (MetaDrive's car, the default), ``fitted bicycle``, ``kinematic`` (the preset's) or ``custom``."""
    names = {DynamicsConfig(): "raycast", DynamicsConfig(model="bicycle"): "fitted bicycle", DynamicsConfig.kinematic(): "kinematic"}
    return names.get(dynamics, "custom")


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate a checkpoint or exported policy deterministically on test seeds and print the six metrics."""

    if args.episodes < 1:
        raise ValueError(f"bad --episodes {args.episodes}; allowed: an integer >= 1")
    check_preset(args.preset)
    seeds = args.seeds if args.seeds else eval_test_seeds(args.episodes)
    not_test = [s for s in seeds if s < TEST_SEED_BASE]
    if not_test:
        print(
            f"warning: --seeds {not_test[:5]}{' ...' if len(not_test) > 5 else ''} are training or validation seeds "
            f"(test seeds are >= {TEST_SEED_BASE}); figures on them are not test results",
            file=sys.stderr,
        )
    overrides = parse_overrides(args.set)
    if args.num_agents is not None:
        overrides["num_agents"] = args.num_agents
    if args.backend is not None:
        overrides["backend"] = args.backend
    source = Path(args.policy)
    config = _evaluation_config(source, args.scenario, overrides, args.preset)
    policy = as_policy(source)
    print(
        f"evaluate: {source} on {config.scenario} ({config.num_agents} agents, backend {config.backend}), "
        f"seeds {seeds[0]}..{seeds[-1]} ({len(seeds)})"
    )
    origin = f"--preset {args.preset}" if args.preset else "the policy's training config"
    print(
        f"  settings ({origin}): lidar_range {config.lidar_range:g}, crash_penalty {config.crash_penalty:g}, "
        f"out_of_road_penalty {config.out_of_road_penalty:g}, dynamics {_dynamics_name(config.dynamics)}, "
        f"max_agent_steps {config.max_agent_steps}"
    )
    t0 = time.perf_counter()
    per_episode = evaluate_policy(policy, config, seeds)
    agg = aggregate(per_episode)
    print(f"\n{len(seeds)} episodes in {time.perf_counter() - t0:.1f} s; mean (std) per episode:")
    for key, label, fmt in CONSOLE_ROWS:
        m, sd = (agg[key]["mean"], agg[key]["std"]) if key in agg else (math.nan, math.nan)
        total = f"  {sum(e[key] for e in per_episode):.0f} in all" if fmt == "count" and key in agg else ""
        print(f"  {label:<18}{shown(m, fmt):>10} ({shown(sd, fmt)}){total}")
    print(
        f"  avg travel steps: finished vehicles, one that did not arrive counting as max_agent_steps ({config.max_agent_steps}), "
        "as COIN's Table 5.1; travel (arrived): arrivals only\n"
        "  time-outs: vehicles done without arriving, crashing or leaving the road (their step limit or the forced stop)"
    )
    if args.out:
        Path(args.out).write_text(json.dumps({"seeds": seeds, "episodes": per_episode, "aggregate": agg}, indent=2, default=float))
        print(f"  per-episode results: {args.out}")
    return 0


def cmd_probe(args: argparse.Namespace) -> int:
    """Print what a TD3-family checkpoint's critics say at its deterministic policy's stopped vehicles."""
    t0 = time.perf_counter()
    probe = probe_checkpoint(Path(args.checkpoint), args.episodes, args.speed_below)
    share = probe.stopped_steps / max(1, probe.vehicle_steps)
    print(
        f"probe: {args.checkpoint}, {args.episodes} test seeds, deterministic actions: {probe.stopped_steps} of "
        f"{probe.vehicle_steps} vehicle-steps ({share:.1%}) below {args.speed_below:g} m/s"
    )
    if probe.stopped_steps:
        steer, throttle = probe.policy_action
        print(
            f"  the policy's action there: steering {steer:+.3f}, throttle {throttle:+.3f} (mean |pre-tanh| "
            f"{probe.policy_preact_abs[0]:.2f}, {probe.policy_preact_abs[1]:.2f}); "
            f"Q_local {probe.policy_q_local:.3f}, Q_global {probe.policy_q_global:.3f}"
        )
        print("  same steering, throttle replaced: mean Q and the share of those steps where it beats the policy's action")
        print(f"  {'throttle':>8} {'Q_local':>9} {'Q_global':>9} {'local':>6} {'global':>6} {'actor objective':>16}")
        for r in probe.table.itertuples():
            print(
                f"  {r.throttle:>+8.1f} {r.q_local:>9.3f} {r.q_global:>9.3f} {r.local_prefers:>6.2f} "
                f"{r.global_prefers:>6.2f} {r.objective_prefers:>16.2f}"
            )
    print(f"summary: {probe.stopped_steps} stopped vehicle-steps probed in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """Export a checkpoint's deterministic actor to a Ray-free file and check it against the RLModule."""

    check_format(args.format, args.out)  # before loading anything
    checkpoint = Path(args.checkpoint)
    meta = read_metadata(checkpoint)
    module = load_module(checkpoint)
    actor, reference, extra = export_actor(module)
    keep = {k: meta[k] for k in ("algo", "scenario", "seed", "env_config") if k in meta}
    out = export_policy(actor, args.out, args.format, meta=keep | extra | {"checkpoint": str(checkpoint.resolve())})
    exported = load_policy(out)
    obs = np.random.default_rng(0).uniform(0.0, 1.0, (256, exported.obs_dim)).astype(np.float32)
    gap = float(np.abs(reference(obs) - exported(obs)).max())
    print(f"export: {checkpoint} -> {out} ({args.format}, {out.stat().st_size / 1024:.0f} KiB, obs {exported.obs_dim})")
    if "lcf" in extra:
        lcf = extra["lcf"]
        print(
            f"  CoPO: the actor takes [obs | (lcf + 1) / 2]; evaluate draws each vehicle's LCF from "
            f"N({lcf['mean']:.4f}, {lcf['std']:.4f}) in the file's metadata (train with --set eval_lcf=mean for the mean LCF)"
        )
    print(f"  parity: max |action - RLModule.forward_inference| on 256 random obs = {gap:.1e}")
    if gap > 1e-5:
        raise ValueError(f"exported {args.format} actor differs from the RLModule by {gap:.1e} (> 1e-5); {out} is not trustworthy")
    return 0


def cmd_pair(args: argparse.Namespace) -> int:
    """Write a switching-policy file: the short-range policy inside --switch-radius of the target, the long-range one outside."""

    out = write_pair(args.out, args.long, args.short, args.switch_radius)
    policy = as_policy(out)  # loads both parts: a bad source fails now, not in the evaluation
    print(f"pair: long {args.long} + short {args.short}, switch at {policy.switch_radius} m -> {out}")
    return 0


def cmd_evaluate_arena(args: argparse.Namespace) -> int:
    """Run the seed-2 evaluation suite (Tables I and II) on one or more policies; per-policy case tables, one side-by-side table."""

    cases = parse_cases(args.cases)
    labels = policy_labels(args.policy)
    if args.scenarios_per_case < 1:
        raise ValueError(f"bad --scenarios-per-case {args.scenarios_per_case}; allowed: an integer >= 1")
    observes = {  # a bad source or entity count fails now, before any policy is evaluated
        source: policy_config(load_arena_policy(source), args.max_steps, args.protocol, args.generator, args.observed_entities)
        for source in args.policy
    }
    out = Path(args.out)
    folders = {label: "." if len(labels) == 1 else label for label in labels}  # one policy: its files in --out itself
    print(
        f"evaluate-arena: {', '.join(args.policy)}; {len(cases)} cases x {args.scenarios_per_case} scenarios, up to {args.max_steps} "
        f"steps, {args.protocol} protocol, {args.generator} scenarios -> {out}"
    )
    t0 = time.perf_counter()
    summaries = {}
    for source, label in zip(args.policy, labels):
        if len(labels) > 1:
            print(f"\n{label} ({source})")
        rows = evaluate_suite(
            source,
            cases,
            args.scenarios_per_case,
            args.max_steps,
            args.workers,
            protocol=args.protocol,
            generator=args.generator,
            observed=args.observed_entities,
        )
        where = out / folders[label]
        where.mkdir(parents=True, exist_ok=True)
        pd.DataFrame(rows).to_csv(where / "arena_scenarios.csv", index=False)
        summaries[label] = summary = summarize(rows)
        summary.to_csv(where / "arena_cases.csv", index=False)
        header = f"Policy: `{source}`; {args.scenarios_per_case} test scenarios per case; {args.protocol} protocol.\n\n"
        if observes[source].observed_entities != 1:
            k = observes[source].observed_entities
            header += f"Each vehicle observes its {k} closest entities (`observed_entities`; the paper's observation: 1).\n\n"
        if observes[source].candidate_features:
            header += (
                "Each vehicle also observes the clearance of the planning filter's 22 candidate rollouts "
                "(`candidate_features`; not in the paper's observation).\n\n"
            )
        if args.generator != "agnn":
            header += f"Scenarios of the `{args.generator}` generator, not the paper's suite: the paper's columns do not apply.\n\n"
        (where / "arena_table.md").write_text(header + markdown_table(summary))
        if args.plots:
            plots = plot_scenarios(
                source, cases, args.plots, where / "plots", args.max_steps, args.protocol, args.generator, args.observed_entities
            )
            print(f"  trajectory plots: {len(plots)} in {where / 'plots'}")
    settings = {
        "policies": list(args.policy),
        "folders": folders,
        "cases": [f"{n}x{m}" for n, m in cases],
        "scenarios_per_case": args.scenarios_per_case,
        "max_steps": args.max_steps,
        "protocol": args.protocol,
        "generator": args.generator,
        "observed_entities": args.observed_entities,
        "command": getattr(args, "command_line", None),
    }
    _, markdown = write_side_by_side(out, summaries, settings)
    page = write_arena_html(out / ARENA_PAGE, [load_arena_eval(out)], settings["command"])
    print(f"\n{len(labels)} policies x {len(cases)} cases x {args.scenarios_per_case} scenarios in {time.perf_counter() - t0:.0f} s")
    print(markdown_table(summaries[labels[0]]) if len(labels) == 1 else markdown)
    for label in labels:
        where = out / folders[label]
        print(f"  {label}: per-scenario rows {where / 'arena_scenarios.csv'}, case table {where / 'arena_table.md'}")
    print(f"  side by side: {out / 'arena_side_by_side.md'} (and .csv); page: {page}")
    return 0


def sweep_scale(scale: str | None, smoke: bool) -> str:
    """The scale asked for by ``--scale`` and ``--smoke`` (default paper); a ValueError when they disagree."""
    if smoke and scale not in (None, "smoke"):
        raise ValueError(f"--smoke with --scale {scale}; allowed: one of them (--smoke is --scale smoke)")
    return "smoke" if smoke else scale or "paper"


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run or resume a Tune sweep of one paper experiment; print where results went and each trial's figures."""

    summary = run_sweep(
        args.experiment,
        scenario=args.scenario,
        scale=sweep_scale(args.scale, args.smoke),
        methods=tuple(args.algos) if args.algos else None,
        seeds=tuple(args.seeds) if args.seeds else None,
        steps=args.steps,
        overrides=parse_overrides(args.set),
        storage=args.storage,
        name=args.name,
        address=args.address,
        max_concurrent=args.max_concurrent,
        resume=args.resume,
        restart=tuple(args.restart),
        num_cpus=args.num_cpus,
        command=getattr(args, "command_line", None),
        wandb_project=args.wandb,
        mlflow_uri=args.mlflow,
    )
    print(f"\nsweep summary: {summary['experiment_dir']} ({summary['wall_s']:.0f} s, {summary['errors']} errored trials)")
    for t in summary.get("trials", []):
        state = "done" if t["finished"] else "UNFINISHED"
        print(
            f"  {t['name']:<28} {state:<10} env steps {t['env_steps']:>9}  train success {t['train_success_rate']:.3f}  "
            f"eval success {t['eval_success_rate']:.3f}  {t['checkpoint']}"
        )
    if "generalization_csv" in summary:
        print(f"  generalization table: {summary['generalization_csv']}")
    unfinished = [t["name"] for t in summary.get("trials", []) if not t["finished"]]
    if summary["errors"] or unfinished:
        print(f"  not finished: {', '.join(unfinished) or summary['errors']}; continue with --resume")
        return 1
    return 0


def cmd_generalize(args: argparse.Namespace) -> int:
    """Evaluate every final checkpoint of a sweep at each agent count; write the tidy generalization CSV."""

    out = write_generalization(Path(args.experiment_dir), counts=args.counts, test_seeds=args.test_seeds)
    print(f"generalization table: {out}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    """Evaluate sweeps (or read results) and write the paper's tables, tests, figures and report.html."""

    options = ReportOptions(
        method=args.method,
        counts=tuple(args.counts) if args.counts else None,
        test_seeds=args.test_seeds,
        workers=args.workers,
        alpha=args.alpha,
        tsne_samples=args.tsne_samples,
        tsne_episodes=args.tsne_episodes,
        transfer=args.transfer,
        transfer_test_seeds=args.transfer_test_seeds,
        select=args.select,
        validation_episodes=args.validation_episodes,
        command=getattr(args, "command_line", None),
    )
    arena = [Path(p) for p in args.sources if is_arena_eval(p)]  # evaluate-arena outputs: the arena page
    sweeps = [Path(p) for p in args.sources if not is_arena_eval(p)]
    if arena:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        page = write_arena_html(out / ARENA_PAGE, [load_arena_eval(p) for p in arena], options.command)
        print(f"arena report: {len(arena)} evaluate-arena run(s) -> {page}")
        if not sweeps:
            return 0
    summary = build_report(sweeps, Path(args.out), options)
    print(
        f"\nreport summary: {summary['episodes']} test episodes of {summary['models']} models "
        f"in {summary['wall_s']:.0f} s -> {summary['out']}"
    )
    for key, value in summary["success"].items():
        print(f"  success {key:<40} {100 * value:6.2f} %")
    drawn = [k for k, v in summary["figures"].items() if not v.startswith("not drawn")]
    print(f"  figures: {len(drawn)} of {len(summary['figures'])} drawn; page: {Path(summary['out']) / 'report.html'}")
    for name, value in summary["figures"].items():
        if value.startswith("not drawn"):
            print(f"    {name}: {value}")
    for f in summary["failures"]:
        where = f" on {f['backend']}" if f.get("backend") else ""
        print(f"  NOT EVALUATED{where} {f.get('trial') or f.get('checkpoint')}: {f['error']}")
    for f in summary.get("unreadable", []):
        print(f"  UNREADABLE {f['path']}: {f['error']} (left out of the learning curves)")
    return 1 if summary["failures"] or summary.get("unreadable") else 0


def _check_command(command: list[str]) -> None:
    """Refuse a coin_app command that does not parse, before it is sent to a cluster."""
    try:
        build_parser().parse_args(command)
    except SystemExit as exc:
        raise ValueError(f"bad coin_app command {' '.join(command)!r} (see python -m coin_app --help)") from exc


def cmd_submit(args: argparse.Namespace) -> int:
    """Submit a coin_app command as a Ray job; print the job id (and follow it with --wait)."""

    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    address = args.address or jobs.DEFAULT_ADDRESS
    job_id = jobs.submit(command, address, args.install, args.submission_id, check_command=_check_command)
    print(f"submitted job {job_id} to {address}: python -m coin_app {' '.join(command)}")
    print(f"  follow it: python -m coin_app job logs {job_id} --address {address}")
    if not args.wait:
        print(job_id)
        return 0
    state = jobs.wait(job_id, address, args.timeout)
    print(f"\njob {job_id} ended: {state}")
    return 0 if state == "SUCCEEDED" else 1


def cmd_job(args: argparse.Namespace) -> int:
    """Status, logs or stop of a submitted job (``ray job status|logs|stop``)."""

    try:
        if args.action == "status":
            print(jobs.status(args.job_id, args.address))
        elif args.action == "logs":
            print(jobs.logs(args.job_id, args.address), end="")
        else:
            print(f"stop requested for {args.job_id}" if jobs.stop(args.job_id, args.address) else f"{args.job_id} was not running")
    except RuntimeError as exc:  # the job server's answer for an unknown id
        raise ValueError(f"job {args.job_id}: {exc}") from exc
    return 0


def cmd_scenarios(args: argparse.Namespace) -> int:
    """List the scenarios, presets and every config key with its default."""

    for name, n in DEFAULT_NUM_AGENTS.items():
        cfg = make_config(name)
        print(f"{name:<13} {n:>3} agents  obs {cfg.obs_dim}  registered as coin-{name}-v0")
    print(f"presets: {', '.join(PRESETS)}")
    print("config keys (--set key=value):")
    cfg = ScenarioConfig()
    for f in fields(ScenarioConfig):
        if f.name not in ("scenario", "dynamics"):
            print(f"  {f.name:<20} {getattr(cfg, f.name)!r}")
    print("  dynamics             a dict of DynamicsConfig fields, e.g. --set \"dynamics={'max_speed_kmh': 60}\"")

    arena = ArenaConfig()
    print(f"arena          {arena.num_vehicles:>3} vehicles, {arena.num_obstacles} obstacles  obs {arena.obs_dim}  coin-arena-v0 (nav_ppo)")
    print("arena keys (--set key=value):")
    for f in fields(ArenaConfig):
        if f.name != "reward":
            print(f"  {f.name:<20} {getattr(arena, f.name)!r}")
    print("  reward               a dict of RewardConfig fields (Eqs. 2-6), e.g. --set \"reward={'success_reward': 100}\"")
    for name, spec in registry.ALGORITHMS.items():
        print(f"\n{name} keys (--set key=value; {spec.description}; scenarios: {', '.join(spec.scenarios)}):")
        for key, (default, meaning) in spec.hyperparameters.items():
            print(f"  {key:<30} {default!r:<14} {meaning}")
    print("\nkeys of every algorithm (how it samples, where its learner runs):")
    for key, (default, meaning) in registry.COMMON_KEYS.items():
        print(f"  {key:<30} {default!r:<14} {meaning}")
    return 0


class DefaultsFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default, unless its help already says it or it is a flag (default False)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        empty = action.default is None or action.default is False or action.default == [] or action.default == argparse.SUPPRESS
        if "default" in text or empty or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class DefaultsParser(argparse.ArgumentParser):
    """A command's parser whose --help shows every option's default."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", DefaultsFormatter)
        super().__init__(*args, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every command."""
    parser = argparse.ArgumentParser(
        prog="python -m coin_app",
        description="COIN / CIG-TD3 multi-agent driving on Ray RLlib.",
        epilog="--debug (anywhere on the line): show the traceback of an error instead of its one-line message",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=DefaultsParser)
    sub.required = True

    demo = sub.add_parser("demo", help="drive a scenario with the heuristic driver; metrics, GIF and trajectory plot")
    demo.add_argument("--scenario", default="intersection", help="intersection | roundabout | bottleneck")
    demo.add_argument("--preset", default="paper", help="paper | metadrive_compat | kinematic")
    demo.add_argument("--num-agents", type=int, default=None, help="vehicles at reset (default: the scenario's)")
    demo.add_argument("--steps", type=int, default=300, help="env steps to run (stops earlier if the episode ends)")
    demo.add_argument("--seed", type=int, default=0, help="episode seed")
    demo.add_argument("--out", default="runs/demo", help="output directory")
    demo.add_argument("--gif-every", type=int, default=2, help="render every k-th step into the GIF")
    demo.add_argument("--no-gif", action="store_true", help="skip the animation")
    demo.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="scenario config overrides")
    demo.set_defaults(func=cmd_demo)

    tr = sub.add_parser(
        "train", help="train an algorithm (cig_td3, itd3, traco, ippo, cppo, mfpo, copo, nav_ppo) with checkpoints and --resume"
    )
    tr.add_argument("--algo", default="cig_td3", help="cig_td3 | itd3 | traco | ippo | cppo | mfpo | copo | nav_ppo (arena)")
    tr.add_argument("--scenario", default="intersection", help="intersection | roundabout | bottleneck | arena (nav_ppo)")
    tr.add_argument("--num-agents", type=int, default=None, help="vehicles (default: the scenario's)")
    tr.add_argument("--backend", default="native", help="native | metadrive (needs requirements-metadrive.txt)")
    tr.add_argument("--steps", type=int, default=1_000_000, help="env steps to train for")
    tr.add_argument("--seed", type=int, default=0, help="training seed, an integer in [0, 90000) (higher ones are evaluation seeds)")
    tr.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="scenario or algorithm overrides (see docs)")
    tr.add_argument("--out", default=None, help="run directory (default runs/<algo>_<scenario>_s<seed>)")
    tr.add_argument("--checkpoint-every", type=int, default=10, help="checkpoint every K training iterations")
    tr.add_argument("--max-minutes", type=float, default=None, help="stop (with a checkpoint) after this much wall time")
    tr.add_argument("--resume", default=None, help="checkpoint directory to continue from (same algorithm, scenario and network)")
    tr.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out (refused without --resume or this)")
    tr.add_argument(
        "--progress",
        choices=("auto", "always", "never"),
        default="auto",
        help="progress bar over env steps, with the updates inside each iteration (auto: on a terminal only)",
    )
    tr.add_argument(
        "--quick",
        action="store_true",
        help="the algorithm's small settings that show learning within minutes (4 agents, horizon 300, small networks, "
        "TD3 family: warm-up 500); --set values override them",
    )
    tr.add_argument(
        "--threads",
        type=int,
        default=1,
        help="torch threads of the training process (1; more only if benchmarks/learner_update.py shows it helps)",
    )
    tr.add_argument("--address", default=None, help="a running Ray cluster (default: a local session over all of this machine's cores)")
    tr.set_defaults(func=cmd_train)

    ev = sub.add_parser("evaluate", help="evaluate a checkpoint or exported policy on test seeds (deterministic actions)")
    ev.add_argument("policy", help="a checkpoint directory or an exported .npz file")
    ev.add_argument("--scenario", default=None, help="scenario (default: the one the policy was trained on)")
    ev.add_argument("--backend", default=None, help="native | metadrive (default: the training backend)")
    ev.add_argument(
        "--preset",
        default=None,
        help=f"{' | '.join(PRESETS)}: evaluate with this preset's settings in place of the training config's preset and the keys "
        "presets set (e.g. metadrive_compat: lidar_range 40); --set still wins (default: the policy's own training config)",
    )
    ev.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="scenario config overrides")
    ev.add_argument("--episodes", type=int, default=20, help="number of test seeds (paper: 20)")
    ev.add_argument("--seeds", type=int, nargs="*", default=None, help="explicit seeds (default: the fixed test seeds)")
    ev.add_argument("--num-agents", type=int, default=None, help="evaluate at another agent count (generalization)")
    ev.add_argument("--out", default=None, help="write per-episode results to this JSON file")
    ev.set_defaults(func=cmd_evaluate)

    pr = sub.add_parser("probe", help="a TD3-family checkpoint's critics at its stopped vehicles: do they prefer braking or driving on?")
    pr.add_argument("checkpoint", help="a CIG-TD3 or ITD3 checkpoint directory (native backend)")
    pr.add_argument("--episodes", type=int, default=10, help="test seeds to run (default 10)")
    pr.add_argument("--speed-below", type=float, default=0.5, help="a vehicle counts as stopped below this speed (m/s)")
    pr.set_defaults(func=cmd_probe)

    ex = sub.add_parser("export", help="export a checkpoint's actor for Ray-free inference")
    ex.add_argument("checkpoint", help="a checkpoint directory written by train or a sweep")
    ex.add_argument(
        "--format",
        default="numpy",
        help="numpy (.npz weights, numpy forward pass), torchscript (.pt, needs torch) or onnx (.onnx, needs requirements-onnx.txt)",
    )
    ex.add_argument("--out", required=True, help="output file with the format's suffix: policy.npz, policy.pt or policy.onnx")
    ex.set_defaults(func=cmd_export)

    pa = sub.add_parser("pair", help="combine a long- and a short-range arena policy into one switching policy file")
    pa.add_argument("long", help="long-range policy: checkpoint directory or exported .npz")
    pa.add_argument("short", help="short-range (parking) policy: checkpoint directory or exported .npz")
    pa.add_argument("--switch-radius", type=float, default=7.5, help="metres to the target below which the short-range policy acts")
    pa.add_argument("--out", required=True, help="pair file to write (.json)")
    pa.set_defaults(func=cmd_pair)

    ea = sub.add_parser("evaluate-arena", help="the seed-2 paper's 24-case arena test suite (Tables I and II) for policies, side by side")
    ea.add_argument(
        "policy",
        nargs="+",
        help="one or more of: heuristic | avoiding | planning (the scripted drivers) | agnn (the A-GNN baseline's released weights) | "
        "checkpoint directory | exported .npz | pair .json",
    )
    ea.add_argument("--cases", default="all", help="all (the paper's 24) or e.g. 4x3,20x8")
    ea.add_argument("--scenarios-per-case", type=int, default=100, help="fixed test scenarios per case (the paper: 4062)")
    ea.add_argument(
        "--max-steps", type=int, default=400, help="steps of 0.1 s per scenario (400 = 40 s; agnn: the same time in its 0.2 s steps)"
    )
    ea.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        default="arena",
        help="arena: the seed paper's success test (1.25 m, 0.2 rad, 0.05 m/s; vehicles park); "
        "agnn: the A-GNN paper's (final state within 1.25 m and 0.2 rad, no speed test, early stop when all are still)",
    )
    ea.add_argument(
        "--generator",
        choices=GENERATORS,
        default="agnn",
        help="agnn: the paper's suite (the A-GNN test generator); short: the parking stage's starts (1-7.5 m from the target, "
        "any heading) on the same held-out seeds, to score a short-range policy alone (not comparable with the paper's tables)",
    )
    ea.add_argument(
        "--observed-entities",
        type=int,
        default=None,
        help="entities each vehicle observes, closest first: for scripted drivers (default 1, the paper's); "
        "learned policies observe what they were trained on",
    )
    ea.add_argument("--workers", type=int, default=2, help="worker processes (one CPU thread each)")
    ea.add_argument("--out", default="runs/arena_eval", help="output directory")
    ea.add_argument("--plots", type=int, default=0, help="trajectory plots of the first K test scenarios of each case")
    ea.set_defaults(func=cmd_evaluate_arena)

    sw = sub.add_parser("sweep", help="run (or --resume) a Ray Tune sweep: seeds | ablations | generalization")
    sw.add_argument("experiment", help="seeds, ablations or generalization (tuning/)")
    sw.add_argument("--scenario", default="intersection", help="intersection, roundabout or bottleneck")
    sw.add_argument("--algos", nargs="*", default=None, help="methods to sweep (default: the experiment's, cig_td3)")
    sw.add_argument("--seeds", type=int, nargs="*", default=None, help="training seeds (default: the scale's; paper: 0..7)")
    sw.add_argument("--steps", type=int, default=None, help="env steps per trial (default: the scale's; paper: 1,000,000)")
    sw.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides for every trial")
    sw.add_argument(
        "--scale",
        default=None,
        help="paper (the paper's settings, a cluster), reduced (the one-machine protocol of docs/results) or smoke (tests, CI)",
    )
    sw.add_argument("--smoke", action="store_true", help="the same as --scale smoke")
    sw.add_argument("--address", default=None, help="Ray cluster to run on: auto, HOST:PORT or ray://HOST:PORT (default: a local Ray)")
    sw.add_argument("--storage", default=None, help="results root: a path or a URI such as s3://bucket/sweeps (default runs/sweeps)")
    sw.add_argument("--name", default=None, help="experiment directory name (default <experiment>-<scenario>[-<scale>])")
    sw.add_argument("--max-concurrent", type=int, default=None, help="trials running at once (default: as many as fit)")
    sw.add_argument("--num-cpus", type=int, default=None, help="CPUs of the local Ray (default: all)")
    sw.add_argument("--resume", action="store_true", help="continue the named sweep: finished trials stay, others resume")
    sw.add_argument(
        "--restart",
        nargs="+",
        default=[],
        metavar="METHOD",
        help="with --resume: run these methods' trials again from scratch (after a fix); their old directories move to replaced/",
    )
    sw.add_argument("--wandb", default=None, metavar="PROJECT", help="also log trials to this W&B project (needs wandb)")
    sw.add_argument("--mlflow", default=None, metavar="URI", help="also log trials to this MLflow tracking URI (needs mlflow)")
    sw.set_defaults(func=cmd_sweep)

    ge = sub.add_parser("generalize", help="evaluate a sweep's final checkpoints at other agent counts (tidy CSV)")
    ge.add_argument("experiment_dir", help="a sweep's experiment directory")
    ge.add_argument("--counts", type=int, nargs="*", default=None, help="agent counts (default: the sweep's grid)")
    ge.add_argument("--test-seeds", type=int, default=None, help="episodes per checkpoint and count (default: the sweep's, 20)")
    ge.set_defaults(func=cmd_generalize)

    rp = sub.add_parser("report", help="evaluate sweeps on the test seeds; tables, t-tests, figures, marl-eval JSON, report.html")
    rp.add_argument(
        "sources",
        nargs="+",
        help="sweep directories, directories of sweeps, results.csv files of earlier reports, or evaluate-arena output directories",
    )
    rp.add_argument("--out", required=True, help="output directory")
    rp.add_argument("--method", default="cig_td3", help="the method tested against every baseline (default cig_td3)")
    rp.add_argument(
        "--counts", type=int, nargs="*", default=None, help="also evaluate at these agent counts (default: a generalization sweep's)"
    )
    rp.add_argument("--test-seeds", type=int, default=None, help="test episodes per model and cell (default: the sweep's, 20)")
    rp.add_argument("--workers", type=int, default=2, help="evaluation processes")
    rp.add_argument("--alpha", type=float, default=0.01, help="significance level before the Bonferroni correction")
    rp.add_argument("--tsne-samples", type=int, default=500, help="CVAE latent samples per scenario (paper: 1500)")
    rp.add_argument("--tsne-episodes", type=int, default=4, help="test episodes the latents are collected from")
    rp.add_argument("--transfer", default=None, help="also evaluate every model on this backend (metadrive): the native -> MetaDrive gap")
    rp.add_argument("--transfer-test-seeds", type=int, default=5, help="test episodes per model on the --transfer backend")
    rp.add_argument(
        "--select",
        default="final",
        help="the checkpoint of each trial scored on the test seeds: final (default) | validation (the one best on validation seeds)",
    )
    rp.add_argument("--validation-episodes", type=int, default=10, help="validation seeds per checkpoint with --select validation")
    rp.set_defaults(func=cmd_report)

    sb = sub.add_parser("submit", help="submit a coin_app command to a Ray cluster as a job (ray job submit); prints the job id")
    sb.add_argument("--address", default=None, help="job server URL (the dashboard), default http://127.0.0.1:8265")
    sb.add_argument("--install", default="pip", choices=["pip", "none"], help="pip: install requirements.txt's pins in the job env")
    sb.add_argument("--submission-id", default=None, help="job id to use (default: one from Ray)")
    sb.add_argument("--wait", action="store_true", help="follow the job's logs until it ends; exit 0 only if it succeeded")
    sb.add_argument("--timeout", type=float, default=24 * 3600.0, help="seconds --wait follows the job at most")
    sb.add_argument("command", nargs=argparse.REMAINDER, help="-- then the coin_app command, e.g. -- sweep seeds --smoke")
    sb.set_defaults(func=cmd_submit)

    jb = sub.add_parser("job", help="status, logs or stop of a submitted job")
    jb.add_argument("action", choices=["status", "logs", "stop"])
    jb.add_argument("job_id", help="the id submit printed")
    jb.add_argument("--address", default=None, help="job server URL, default http://127.0.0.1:8265")
    jb.set_defaults(func=cmd_job)

    scen = sub.add_parser("scenarios", help="list scenarios, presets, their config keys and every algorithm's keys with defaults")
    scen.set_defaults(func=cmd_scenarios)
    return parser


USER_ERRORS = (ValueError, ImportError, OSError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile)


def one_line(exc: BaseException) -> str:
    """An exception as one line: its first line, with the type for errors that are not ValueErrors."""
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if isinstance(exc, OSError) and exc.filename is not None and str(exc.filename) not in text:
        text += f": {exc.filename}"
    return text if isinstance(exc, ValueError) else f"{type(exc).__name__}: {text}"


def main(argv: list[str] | None = None) -> int:
    """Entry point; bad input exits with status 2 and a one-line message (``--debug`` anywhere: the traceback too)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    parser = build_parser()
    args = parser.parse_args(argv)
    args.command_line = shlex.join(["python", "-m", "coin_app", *argv])
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if debug:
            traceback.print_exc()
        known = isinstance(exc, USER_ERRORS)
        hint = "" if debug else " (--debug shows the traceback)"
        print(f"error: {one_line(exc)}" + ("" if known else f"; an unexpected error{hint}"), file=sys.stderr)
        return 2 if known else 1


if __name__ == "__main__":
    sys.exit(main())
