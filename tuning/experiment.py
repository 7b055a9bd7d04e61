"""What a sweep is: methods x variants x seeds on one scenario, at a named scale, as a Tune param space.

An :class:`Experiment` names the methods (registry algorithms), the variants (named override
sets: ablations) and, per scale, the seeds, the env-step budget per trial (one for every method,
or one per algorithm family), the checkpoint cadence and, for generalization, the agent counts and
test seeds to evaluate the final checkpoints at. :meth:`Experiment.param_space` turns it into the
dict Tune expands with ``grid_search`` (a budget that differs between the methods is a
:func:`per_method` value, resolved per trial); :func:`expand_grid` expands the same grid in plain
Python so every trial's config is validated (``training.build_config``) before any work starts.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from typing import Any

from coin_app.algorithms import registry
from coin_app.sim.scenes import DRIVING_SCENARIOS

# the scales an experiment may have, largest first, with what each is for (sweep --scale's help)
SCALES = {
    "paper": "the paper's settings, a cluster",
    "dense": "the intersection at the paper's density on one machine, docs/studies/dense_pilots.md",
    "reduced": "the one-machine protocol of docs/results",
    "smoke": "tests, CI",
}
PER_METHOD = "per_method"  # the key of a param-space value that depends on the trial's method (per_method)

# The scales of each algorithm are presets of its settings (its package's settings.py: paper, dense, reduced, smoke), over the
# quick scenario at the smoke and reduced scales (registry.quick_scenario); the dense scale is the scenario's own defaults
# (the intersection's 30 vehicles, horizon 1000, respawning). The reduced protocol's TD3 family also decays its
# learning rates to REDUCED_LR_FINAL_FRACTION, and its exploration std to the preset's exploration_noise, over the second half
# of each trial's budget (reduced_decay): with constant rates the policies learned, then froze or crashed late
# (docs/results/journal.md).
REDUCED_LR_FINAL_FRACTION = 0.1


@dataclass(frozen=True)
class Scale:
    """One size of an experiment: seeds, env steps per trial, checkpoints and (generalization) evaluation grid."""

    seeds: tuple[int, ...]
    steps: int  # env steps per trial of every method whose family steps_by_family does not name
    checkpoint_every: int  # training iterations between checkpoints (plus one at the end)
    keep: int  # checkpoints kept per trial (the newest, or with keep_best the best by that result key; the latest always stays)
    test_seeds: int = 20  # episodes per (checkpoint, agent count) in the generalization evaluation
    counts: dict[str, tuple[int, ...]] = field(default_factory=dict)  # scenario -> agent counts to evaluate at
    # the scenes the scale was made for (its horizon, budget and settings were chosen there); None = every scene
    made_for: tuple[str, ...] | None = None
    # algorithm family (AlgorithmSpec.family: "td3" | "ppo") -> its env steps per trial, in place of steps
    steps_by_family: dict[str, int] = field(default_factory=dict)
    # the result key (iteration_metrics') whose best `keep` checkpoints a trial keeps besides its latest; None: the newest.
    # A trial whose results lack the key (no periodic evaluation) keeps its newest.
    keep_best: str | None = None
    # scenario settings every trial of the scale takes (a preset, penalties...), below the variant's and --set
    scenario: dict[str, Any] = field(default_factory=dict)
    # algorithm family -> scenario settings its trials take over `scenario` (a family's own training penalties)
    scenario_by_family: dict[str, dict[str, Any]] = field(default_factory=dict)
    # scene -> scenario settings its trials take over `scenario`, below a family's (a scene's own road or observation)
    scenario_by_scene: dict[str, dict[str, Any]] = field(default_factory=dict)

    def budget(self, algo: str) -> int:
        """Env steps per trial of method ``algo``: its family's budget, else ``steps``."""
        return self.steps_by_family.get(registry.get(algo).family, self.steps)

    def __post_init__(self) -> None:
        """Refuse a family or scene name that does not exist (a typo would be ignored silently)."""
        families = {spec.family for spec in registry.ALGORITHMS.values()}
        for by in (self.steps_by_family, self.scenario_by_family):
            unknown = sorted(set(by) - families)
            if unknown:
                raise ValueError(f"unknown algorithm families {unknown}; allowed: {', '.join(sorted(families))}")
        unknown = sorted(set(self.scenario_by_scene) - set(DRIVING_SCENARIOS))
        if unknown:
            raise ValueError(f"unknown scenes {unknown}; allowed: {', '.join(DRIVING_SCENARIOS)}")

    def scenario_for(self, algo: str, scene: str | None = None) -> dict[str, Any]:
        """The scenario settings of method ``algo``'s trials on ``scene``: ``scenario``, then the scene's
        ``scenario_by_scene``, then the method's family's ``scenario_by_family``."""
        family = registry.get(algo).family
        return dict(self.scenario) | dict(self.scenario_by_scene.get(scene or "", {})) | dict(self.scenario_by_family.get(family, {}))


@dataclass(frozen=True)
class Experiment:
    """A paper experiment as a sweep definition (see module doc)."""

    name: str
    summary: str
    methods: tuple[str, ...]
    scenarios: tuple[str, ...]
    paper: Scale
    smoke: Scale
    reduced: Scale | None = None  # the one-machine protocol (None: this experiment has no reduced scale)
    dense: Scale | None = None  # the paper's density on one machine (None: this experiment has no dense scale)
    variants: dict[str, dict[str, Any]] = field(default_factory=lambda: {"default": {}})
    smoke_variants: tuple[str, ...] | None = None  # a subset of variants at smoke scale (None = all)
    allowed_methods: tuple[str, ...] | None = None  # methods the variants apply to (None = every registry algorithm)

    def scale(self, name: str, scenario: str | None = None) -> Scale:
        """The scale called ``name`` (one of ``SCALES``); a ValueError if it was not made for ``scenario``."""
        scales: dict[str, Scale | None] = {n: getattr(self, n) for n in SCALES}
        allowed = ", ".join(n for n in SCALES if scales[n] is not None)
        if name not in SCALES:
            raise ValueError(f"unknown scale {name!r}; allowed: {allowed}")
        found = scales[name]
        if found is None:
            raise ValueError(f"experiment {self.name!r} has no {name} scale; allowed: {allowed}")
        if scenario is not None and found.made_for is not None and scenario not in found.made_for:
            fits = ", ".join(n for n, sc in scales.items() if sc is not None and sc.made_for is None)
            raise ValueError(
                f"the {name} scale was made for the {' and '.join(found.made_for)} (its horizon, budget and settings were chosen "
                f"there), not the {scenario}; allowed: --scenario {' | '.join(found.made_for)}, or a scale for every scene: {fits}"
            )
        return found

    def variant_names(self, scale: str) -> tuple[str, ...]:
        """The variants swept at ``scale``."""
        return tuple(self.smoke_variants or self.variants) if scale == "smoke" else tuple(self.variants)

    def check(self, scenario: str, methods: tuple[str, ...], seeds: tuple[int, ...] | None) -> None:
        """A ValueError naming the bad scenario, method or seed list and what is allowed."""
        if scenario not in self.scenarios:
            raise ValueError(f"experiment {self.name!r} runs on {', '.join(self.scenarios)}; got scenario {scenario!r}")
        for m in methods:
            registry.get(m)
            if self.allowed_methods is not None and m not in self.allowed_methods:
                raise ValueError(f"experiment {self.name!r} sweeps variants of {', '.join(self.allowed_methods)}; got method {m!r}")
        if not methods:
            raise ValueError(f"experiment {self.name!r} needs at least one method; allowed: {', '.join(sorted(registry.ALGORITHMS))}")
        if seeds is not None and (not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0):
            raise ValueError(f"bad seeds {list(seeds)}; allowed: distinct integers >= 0")

    def base_config(
        self, scenario: str, scale: str, steps: int | dict[str, Any], overrides: dict[str, Any], settings: Any
    ) -> dict[str, Any]:
        """The part of every trial's config that Tune's grid does not vary (``steps`` and the scale's scenario ``settings``,
        :meth:`Scale.scenario_for`: each a value, or a :func:`per_method` one)."""
        return ({"scale_scenario": settings} if settings else {}) | {
            "experiment": self.name,
            "scenario": scenario,
            "scale": scale,
            "steps": steps,
            "overrides": dict(overrides),
            "variant_overrides": {v: dict(self.variants[v]) for v in self.variant_names(scale)},
        }

    def param_space(
        self,
        scenario: str,
        scale: str = "paper",
        methods: tuple[str, ...] | None = None,
        seeds: tuple[int, ...] | None = None,
        steps: int | None = None,
        overrides: dict[str, Any] | None = None,
    ) -> dict[str, Any]:
        """The Tune param space: grid over method x variant x seed; ``steps`` (every trial's budget) or each method's ``Scale.budget``."""
        sc = self.scale(scale, scenario)
        methods = tuple(methods or self.methods)
        self.check(scenario, methods, seeds)
        budgets = per_method({m: int(steps or sc.budget(m)) for m in methods})
        settings = per_method({m: sc.scenario_for(m, scenario) for m in methods})
        return self.base_config(scenario, scale, budgets, overrides or {}, settings) | {
            "algo": grid_search(methods),
            "variant": grid_search(self.variant_names(scale)),
            "seed": grid_search(seeds or sc.seeds),
        }


def grid_search(values: Any) -> dict[str, list[Any]]:
    """Tune's grid axis, ``{"grid_search": [...]}``, what ``tune.grid_search`` returns: written here so that an experiment,
    and ``config --scale``, need no Ray."""
    return {"grid_search": list(values)}


def per_method(values: dict[str, Any]) -> Any:
    """A param-space value by the trial's method (``algo``): the one value when every method has it, else
    ``{PER_METHOD: values}``, which :func:`expand_grid` resolves per trial (and ``tuning.sweep`` as Tune's ``sample_from``)."""
    distinct = {json.dumps(v, sort_keys=True, default=str) for v in values.values()}  # dicts too
    return next(iter(values.values())) if len(distinct) == 1 else {PER_METHOD: dict(values)}


def is_per_method(value: Any) -> bool:
    """Whether a param-space value is a :func:`per_method` mapping."""
    return isinstance(value, dict) and set(value) == {PER_METHOD}


def expand_grid(space: dict[str, Any]) -> list[dict[str, Any]]:
    """Every trial config of a param space: its top-level ``grid_search`` axes expanded in plain Python, then its
    :func:`per_method` values resolved for each trial's method."""
    axes = {k: v["grid_search"] for k, v in space.items() if isinstance(v, dict) and set(v) == {"grid_search"}}
    fixed = {k: v for k, v in space.items() if k not in axes}
    trials = [fixed | dict(zip(axes, combo)) for combo in itertools.product(*axes.values())]
    return [{k: v[PER_METHOD][t["algo"]] if is_per_method(v) else v for k, v in t.items()} for t in trials]


def reduced_decay(steps: int) -> dict[str, Any]:
    """The reduced scale's decay of the learning rates and the exploration std over a trial of ``steps`` env steps: its second half."""
    start = steps // 2
    length = max(1, steps - start)
    rates = {"lr_decay_start": start, "lr_decay_steps": length, "lr_final_fraction": REDUCED_LR_FINAL_FRACTION}
    return rates | {"exploration_noise_decay_start": start, "exploration_noise_decay_steps": length}


def trial_layers(config: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """The named layers of one trial's registry overrides, lowest first: the scale's, the variant's, the user's ``--set``.

    Every scale is the algorithm's preset of that name (its settings.py), over the quick scenario at the
    smoke and reduced scales (the paper and dense scales: the scenario's defaults); the reduced TD3 family's
    rates and exploration decay over the second half of the budget (``reduced_decay``); paper scale: the PPO
    family's 4 env runners.
    ``python -m coin_app config`` prints them.
    """
    algo, scale = config["algo"], config["scale"]
    spec = registry.get(algo)
    layers: list[tuple[str, dict[str, Any]]] = []
    if scale in ("smoke", "reduced"):
        layers.append((f"quick scenario (registry.quick_scenario({config['scenario']!r}))", registry.quick_scenario(config["scenario"])))
    if scale in spec.presets:
        layers.append((f"preset {scale!r} ({spec.settings.__module__})", spec.presets[scale].changes()))
    if scale == "reduced" and "lr_decay_start" in spec.keys():  # the TD3 family's late decay
        steps = int(config["steps"])
        layers.append((f"reduced scale: decay over the second half of {steps:,} env steps", reduced_decay(steps)))
    if config.get("scale_scenario"):
        label = f"{scale} scale's scenario for the {spec.family} family ({config['experiment']} experiment, tuning/)"
        layers.append((label, dict(config["scale_scenario"])))
    layers.append((f"variant {config['variant']!r}", dict(config["variant_overrides"][config["variant"]])))
    layers.append(("--set", dict(config["overrides"])))
    return layers


def trial_overrides(config: dict[str, Any]) -> dict[str, Any]:
    """The registry overrides of one trial: its :func:`trial_layers` merged, later ones winning."""
    out: dict[str, Any] = {}
    for _, layer in trial_layers(config):
        out |= layer
    return out
