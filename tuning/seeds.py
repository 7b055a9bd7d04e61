"""The main comparison (Table 5.1): every method trained with 8 seeds on one scenario, 1M env steps each.

The reduced scale (``--scale reduced``) is the same comparison on one small machine: 5 seeds on the
4-agent scenario (each algorithm's ``reduced`` preset, its package's settings.py; docs/results/README.md).
"""

from coin_app.sim.scenes import DRIVING_SCENARIOS
from tuning.experiment import Experiment, Scale

SEEDS = Experiment(
    name="seeds",
    summary="methods x 8 training seeds on one scenario (Table 5.1); --algos adds the baselines",
    methods=("cig_td3",),
    scenarios=DRIVING_SCENARIOS,
    paper=Scale(seeds=tuple(range(8)), steps=1_000_000, checkpoint_every=100, keep=2),
    # TD3 family: 10 iterations = 5,000 env steps, all 8 checkpoints kept (the report's validation-seed selection picks among them)
    # the one-machine protocol was chosen on the intersection (docs/results/journal.md): 300-step episodes fit its routes
    reduced=Scale(seeds=tuple(range(5)), steps=40_000, checkpoint_every=10, keep=8, made_for=("intersection",)),
    smoke=Scale(seeds=(0, 1), steps=1000, checkpoint_every=1, keep=1),
)
