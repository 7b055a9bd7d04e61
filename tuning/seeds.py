"""The main comparison (Table 5.1): every method trained with 8 seeds on one scenario, 1M env steps each."""

from tuning.experiment import Experiment, Scale

SEEDS = Experiment(
    name="seeds",
    summary="methods x 8 training seeds on one scenario (Table 5.1); --algos adds the baselines",
    methods=("cig_td3",),
    scenarios=("intersection", "roundabout", "bottleneck"),
    paper=Scale(seeds=tuple(range(8)), steps=1_000_000, checkpoint_every=100, keep=2),
    smoke=Scale(seeds=(0, 1), steps=1000, checkpoint_every=1, keep=1),
)
