"""Zero-shot generalization (Fig. 4/6): train at the scenario's default agent count, then evaluate every final
checkpoint at each initial agent count of the grid (intersection 6-36, roundabout 8-48) on 20 test seeds."""

from tuning.experiment import Experiment, Scale

GENERALIZATION = Experiment(
    name="generalization",
    summary="methods x 8 seeds trained at the default count, evaluated at every agent count of the grid (Fig. 4/6)",
    methods=("cig_td3",),
    scenarios=("intersection", "roundabout", "bottleneck"),
    paper=Scale(
        seeds=tuple(range(8)),
        steps=1_000_000,
        checkpoint_every=100,
        keep=2,
        test_seeds=20,
        counts={
            "intersection": (6, 12, 18, 24, 30, 36),
            "roundabout": (8, 16, 24, 32, 40, 48),
            "bottleneck": (5, 10, 15, 20, 25, 30),
        },
    ),
    smoke=Scale(
        seeds=(0,),
        steps=1000,
        checkpoint_every=1,
        keep=1,
        test_seeds=2,
        counts={s: (2, 4) for s in ("intersection", "roundabout", "bottleneck")},
    ),
)
