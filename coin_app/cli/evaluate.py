"""``evaluate``, ``export``, ``pair`` and ``evaluate-arena``: trained policies on test seeds, and Ray-free files of them."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from coin_app.algorithms.checkpoint_files import read_metadata
from coin_app.algorithms.checkpoints import export_actor, export_metadata, load_module
from coin_app.cli.drive import drive
from coin_app.cli.flags import overrides_of
from coin_app.cli.output import CONSOLE_ROWS, shown
from coin_app.cli.policy_settings import check_preset, driving_config
from coin_app.evaluation.arena_report import PAGE as ARENA_PAGE
from coin_app.evaluation.arena_report import load_arena_eval, policy_labels, write_arena_html, write_side_by_side
from coin_app.evaluation.arena_suite import (
    evaluate_suite,
    load_arena_policy,
    markdown_table,
    parse_cases,
    plot_scenarios,
    policy_config,
    summarize,
)
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.fit import policy_fit
from coin_app.evaluation.limits import MAX_EPISODES, MAX_SCENARIOS_PER_CASE, check_count
from coin_app.evaluation.metrics import aggregate
from coin_app.evaluation.outputs import check_dir_output, check_file_output, write_text_atomic
from coin_app.evaluation.policies import as_policy
from coin_app.inference import export_policy, load_policy
from coin_app.inference.formats import check_format
from coin_app.inference.shipped import is_shipped_name
from coin_app.inference.switching import check_arena_part, write_pair
from coin_app.sim.config import DynamicsConfig
from coin_app.sim.replay import write_replay
from coin_app.sim.seeds import TEST_SEED_BASE, eval_test_seeds


def _policy_meta(source: Path) -> tuple[dict[str, Any], int | None]:
    """A policy's metadata (a checkpoint's or an exported file's) and the observation size its weights take (files only)."""
    if source.is_dir():
        return read_metadata(source), None
    if source.is_file() or is_shipped_name(source):
        exported = load_policy(source)
        return exported.meta, getattr(exported, "obs_dim", None)
    raise ValueError(f"policy {source} does not exist; allowed: a checkpoint directory or an exported policy file (.npz, .pt, .onnx)")


def _evaluation_config(source: Path, scenario: str | None, overrides: dict[str, Any], preset: str | None = None) -> Any:
    """The scenario config to evaluate ``source`` on: its training config (checkpoint / export metadata), ``preset``,
    ``scenario``, then overrides."""
    return driving_config(_policy_meta(source)[0], source, scenario, overrides, preset)


def _dynamics_name(dynamics: DynamicsConfig) -> str:
    """``raycast`` (MetaDrive's car, the default), ``fitted bicycle``, ``kinematic`` (the preset's) or ``custom``."""
    names = {DynamicsConfig(): "raycast", DynamicsConfig(model="bicycle"): "fitted bicycle", DynamicsConfig.kinematic(): "kinematic"}
    return names.get(dynamics, "custom")


def cmd_evaluate(args: argparse.Namespace) -> int:
    """Evaluate a checkpoint or exported policy deterministically on test seeds and print the six metrics."""

    check_count(args.episodes, "--episodes", MAX_EPISODES)
    check_preset(args.preset)
    seeds = args.seeds if args.seeds else eval_test_seeds(args.episodes)
    check_count(len(seeds), "number of --seeds", MAX_EPISODES)
    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        raise ValueError(f"bad --seeds: {repeated} given more than once (an episode would count twice); allowed: distinct seeds")
    if args.replay and Path(args.replay).suffix != ".html":
        raise ValueError(f"bad --replay {args.replay}; allowed: a path ending in .html")
    for flag, out in (("--out", args.out), ("--replay", args.replay)):
        if out:
            check_file_output(Path(out), [Path(args.policy)], flag, "the policy it evaluates")
    if args.out and args.replay and Path(args.out).resolve() == Path(args.replay).resolve():
        raise ValueError(f"--out and --replay name one file {args.out}; allowed: two paths")
    not_test = [s for s in seeds if s < TEST_SEED_BASE]
    if not_test:
        print(
            f"warning: --seeds {not_test[:5]}{' ...' if len(not_test) > 5 else ''} are training or validation seeds "
            f"(test seeds are >= {TEST_SEED_BASE}); figures on them are not test results",
            file=sys.stderr,
        )
    overrides = overrides_of(args.set, {"num_agents": ("--num-agents", args.num_agents), "backend": ("--backend", args.backend)})
    source = Path(args.policy)
    meta, obs_dim = _policy_meta(source)
    config = driving_config(meta, source, args.scenario, overrides, args.preset)
    warnings = policy_fit(meta, config, source, obs_dim)  # a layout it cannot read is refused here
    if args.replay and config.backend != "native":
        raise ValueError(f"--replay records the native simulator; got backend {config.backend!r} (drop --replay or --backend)")
    for line in warnings:
        print(line, file=sys.stderr)
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
    for line in warnings:  # in the summary too, where the figures are read
        print(f"  {line}")
    if args.out:
        results = {"seeds": seeds, "episodes": per_episode, "aggregate": agg, "warnings": warnings}
        write_text_atomic(Path(args.out), json.dumps(results, indent=2, default=float))
        print(f"  per-episode results: {args.out}")
    if args.replay:
        limit = config.force_stop_factor * config.horizon
        run = drive(policy, str(source), config, seeds[0], limit, gif_every=None, log=False)
        page = write_replay(run.trace, run.env.sim.map, args.replay, title=f"{config.scenario}, seed {seeds[0]}: {source}")
        print(f"  replay of seed {seeds[0]}: {page} (open it in a browser)")
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """Export a checkpoint's deterministic actor to a Ray-free file and check it against the RLModule."""

    check_format(args.format, args.out)  # before loading anything
    checkpoint = Path(args.checkpoint)
    check_file_output(Path(args.out), [checkpoint], what="the checkpoint it exports")  # inside, it would tear it (its manifest)
    meta = read_metadata(checkpoint)
    module = load_module(checkpoint)
    actor, reference, extra = export_actor(module)
    # the checkpoint as named on the command line: a relative path stays relative (no machine path in a shipped file)
    out = export_policy(actor, args.out, args.format, meta=export_metadata(meta, extra, str(checkpoint)))
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

    check_file_output(Path(args.out), [Path(args.long), Path(args.short)], what="a policy it pairs")
    for role, source in (("long", args.long), ("short", args.short)):
        part = as_policy(source)  # a bad source fails now, not in the evaluation
        check_arena_part(role, part, read_metadata(Path(source)).get("scenario") if Path(source).is_dir() else None)
    out = write_pair(args.out, args.long, args.short, args.switch_radius)
    policy = as_policy(out)
    print(f"pair: long {args.long} + short {args.short}, switch at {policy.switch_radius} m -> {out}")
    return 0


def cmd_evaluate_arena(args: argparse.Namespace) -> int:
    """Run the seed-2 evaluation suite (Tables I and II) on one or more policies; per-policy case tables, one side-by-side table."""

    cases = parse_cases(args.cases)
    labels = policy_labels(args.policy)
    check_count(args.scenarios_per_case, "--scenarios-per-case", MAX_SCENARIOS_PER_CASE)
    check_dir_output(Path(args.out), [Path(p) for p in args.policy if Path(p).exists()], what="a policy it evaluates")
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
        write_text_atomic(where / "arena_scenarios.csv", pd.DataFrame(rows).to_csv(index=False))
        summaries[label] = summary = summarize(rows)
        write_text_atomic(where / "arena_cases.csv", summary.to_csv(index=False))
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
        write_text_atomic(where / "arena_table.md", header + markdown_table(summary))
        if args.plots:
            plots = plot_scenarios(
                source, cases, args.plots, where / "plots", args.max_steps, args.protocol, args.generator, args.observed_entities, True
            )
            print(f"  trajectory plots and replay pages (.html, open in a browser): {len(plots)} in {where / 'plots'}")
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
