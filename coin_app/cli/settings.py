"""``config``: every merged setting of a run (train's, or one sweep trial's) with the layer it came from."""

from __future__ import annotations

import argparse

from coin_app.algorithms.registry import Setting, merged_settings, quick_settings
from coin_app.cli.flags import overrides_of
from tuning import get_experiment
from tuning.experiment import trial_layers


def run_layers(args: argparse.Namespace) -> tuple[str, list[tuple[str, dict]]]:
    """What the settings are of (a line) and their override layers, lowest first: train's (--quick, --set) or a sweep trial's."""
    overrides = overrides_of(args.set, {"num_agents": ("--num-agents", args.num_agents)})
    if args.scale is None:
        layers = [("--quick", quick_settings(args.algo, args.scenario))] if args.quick else []
        return f"train --algo {args.algo} --scenario {args.scenario}", [*layers, ("--set", overrides)]
    if args.quick:
        raise ValueError("--quick with --scale; allowed: one of them (a scale sets its own small settings)")
    experiment = get_experiment(args.experiment)
    scale = experiment.scale(args.scale, args.scenario)
    experiment.check(args.scenario, (args.algo,), None)
    if args.variant not in experiment.variants:
        raise ValueError(f"unknown variant {args.variant!r} of {args.experiment}; allowed: {', '.join(experiment.variants)}")
    steps = args.steps or scale.budget(args.algo)
    trial = experiment.base_config(args.scenario, args.scale, steps, overrides, scale.scenario_for(args.algo, args.scenario))
    trial |= {"algo": args.algo, "variant": args.variant}
    trial["variant_overrides"] = {args.variant: dict(experiment.variants[args.variant])}
    what = f"sweep {args.experiment} --scale {args.scale}: one {args.algo} trial on {args.scenario}, {steps:,} env steps"
    return what, trial_layers(trial)


def cmd_config(args: argparse.Namespace) -> int:
    """Print every setting of a run after merging its layers, with the layer that set it last."""
    what, layers = run_layers(args)
    settings = merged_settings(args.algo, args.scenario, layers)
    print(f"config: {what}")
    print("layers, lowest first: " + ", ".join(["defaults", *(label for label, layer in layers if layer)]) + " (empty layers left out)")
    width = max(len(s.key) for s in settings)
    for title, group in (("scenario", [s for s in settings if s.scenario_key]), (args.algo, [s for s in settings if not s.scenario_key])):
        print(f"\n{title} settings:")
        for s in group:
            print(f"  {s.key:<{width}}  {_shown(s):<24} {s.origin}")
    changed = [s for s in settings if "default" not in s.origin]
    print(f"\nsummary: {len(settings)} settings, {len(changed)} set above the defaults")
    return 0


def _shown(setting: Setting) -> str:
    """A setting's value as one short cell."""
    text = repr(setting.value)
    return text if len(text) <= 24 else text[:21] + "..."
