"""``train`` and ``probe``: RLlib training runs and a TD3-family checkpoint's critics.

Both import Ray and torch only once their arguments are checked: a refusal costs the parse, not the training machinery.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from coin_app.algorithms.registry import quick_settings, resolve_run
from coin_app.cli.flags import overrides_of
from coin_app.cli.output import format_metrics
from coin_app.evaluation.limits import check_timeout, check_train_budget


def cmd_train(args: argparse.Namespace) -> int:
    """Train an algorithm of the registry; checkpoints and a summary go to ``--out``."""

    flags = {"num_agents": ("--num-agents", args.num_agents), "backend": ("--backend", None if args.backend == "native" else args.backend)}
    overrides = overrides_of(args.set, flags)
    if args.quick:  # the small settings that learn within minutes, beneath the user's --set
        overrides = {**quick_settings(args.algo, args.scenario), **overrides}
    check_train_budget(args.steps, args.max_minutes, args.checkpoint_every, args.threads, args.max_cpu_hours)
    check_timeout(args.connect_timeout, "--connect-timeout")
    resolve_run(args.algo, args.scenario, overrides, args.seed)  # every --set value, the seed and the scenario: Ray-free
    # optional: the training machinery (Ray, RLlib, torch: seconds) only for arguments that passed the checks above
    from coin_app.training import STOPPED_AT_BUDGET, train

    out = Path(args.out or f"runs/{args.algo}_{args.scenario}_s{args.seed}")
    resume = Path(args.resume) if args.resume else None
    print(f"train: {args.algo} on {args.scenario}, {args.steps} env steps, seed {args.seed} -> {out}")
    if args.quick:
        print(f"  --quick: {', '.join(f'{k}={v}' for k, v in quick_settings(args.algo, args.scenario).items())} (your --set wins)")
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
        max_cpu_hours=args.max_cpu_hours,
        threads=args.threads,
        address=args.address,
        overwrite=args.overwrite,
        progress={"auto": None, "always": True, "never": False}[args.progress],
        connect_timeout=args.connect_timeout,
        command=getattr(args, "command_line", None),
    )
    print(f"\nsummary: {summary['env_steps']} env steps in {summary['iterations']} iterations, {summary['wall_s']:.0f} s")
    print(f"  checkpoint: {summary['checkpoint']}")
    if summary.get("stopped", STOPPED_AT_BUDGET) != STOPPED_AT_BUDGET:
        where = f"{summary['env_steps']} of {args.steps} env steps"
        print(f"  stopped early ({summary['stopped']}) at {where}; continue with --resume {summary['checkpoint']}")
    if summary.get("note"):
        print(f"  note: {summary['note']}")
    if summary.get("eval"):
        print("  last periodic evaluation (validation seeds):")
        print(format_metrics(summary["eval"]))
    return 0


def cmd_probe(args: argparse.Namespace) -> int:
    """Print what a TD3-family checkpoint's critics say at its deterministic policy's stopped vehicles."""
    # optional: the probe loads an RLlib module (Ray, torch) only once the command line parsed
    from coin_app.evaluation.critic_probe import probe_checkpoint

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
