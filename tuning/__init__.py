"""Ray Tune sweeps of the COIN paper's experiments: ``seeds``, ``ablations``, ``generalization``.

``python -m coin_app sweep NAME`` runs one (see ``tuning.sweep``); experiments are plain data
(``tuning.experiment.Experiment``) so new ones are a few lines in a new module plus an entry here.
"""

from tuning.ablations import ABLATIONS
from tuning.experiment import Experiment, Scale
from tuning.generalization import GENERALIZATION
from tuning.seeds import SEEDS

EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (SEEDS, ABLATIONS, GENERALIZATION)}


def get_experiment(name: str) -> Experiment:
    """The experiment called ``name``; a ValueError listing the choices otherwise."""
    if name not in EXPERIMENTS:
        raise ValueError(f"unknown experiment {name!r}; allowed: {', '.join(EXPERIMENTS)}")
    return EXPERIMENTS[name]


__all__ = ["EXPERIMENTS", "Experiment", "Scale", "get_experiment"]
