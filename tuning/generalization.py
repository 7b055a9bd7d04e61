"""Zero-shot generalization (Fig. 4/6): train at the scenario's default agent count, then evaluate every final
checkpoint at each initial agent count of its scene's grid (``Scene.generalization_counts``) on 20 test seeds."""

from coin_app.sim.scenes import DRIVING_SCENARIOS, SCENES
from tuning.experiment import Experiment, Scale

GENERALIZATION = Experiment(
    name="generalization",
    summary="methods x 8 seeds trained at the default count, evaluated at every agent count of the grid (Fig. 4/6)",
    methods=("cig_td3",),
    scenarios=DRIVING_SCENARIOS,
    paper=Scale(
        seeds=tuple(range(8)),
        steps=1_000_000,
        checkpoint_every=100,
        keep=2,
        test_seeds=20,
        counts={name: s.generalization_counts for name, s in SCENES.items()},
    ),
    smoke=Scale(
        seeds=(0,),
        steps=1000,
        checkpoint_every=1,
        keep=1,
        test_seeds=2,
        counts=dict.fromkeys(DRIVING_SCENARIOS, (2, 4)),
    ),
)
