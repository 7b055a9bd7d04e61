"""COIN's ablations (Table 5.2, Tables B.1-B.3) as named CIG-TD3 variants, each trained with 8 seeds.

``full`` is COIN itself; ``wo_gat`` drops the global module (mean pooling instead of GAT),
``wo_vae`` the local pairwise module, ``wo_both`` both; ``attention`` replaces the CVAE by
attention-based pairwise fusion (Table B.1); ``sparse_graph`` uses a 40 m radius graph
instead of the full graph (Tables B.2/B.3); ``gcn`` and ``graphsage`` replace the GAT (Table B.3).
"""

from coin_app.sim.scenes import DRIVING_SCENARIOS
from tuning.experiment import Experiment, Scale

VARIANTS = {
    "full": {},
    "wo_gat": {"global_module": "none"},
    "wo_vae": {"local_module": "none", "vae_weight": 0.0},
    "wo_both": {"local_module": "none", "global_module": "none", "vae_weight": 0.0},
    "attention": {"local_module": "attention", "vae_weight": 0.0},
    "sparse_graph": {"graph": 40.0},
    "gcn": {"global_module": "gcn"},
    "graphsage": {"global_module": "graphsage"},
}

ABLATIONS = Experiment(
    name="ablations",
    summary="CIG-TD3 ablation variants x 8 seeds (Table 5.2, B.1-B.3)",
    methods=("cig_td3",),
    scenarios=DRIVING_SCENARIOS,
    paper=Scale(seeds=tuple(range(8)), steps=1_000_000, checkpoint_every=100, keep=2),
    smoke=Scale(seeds=(0,), steps=1000, checkpoint_every=1, keep=1),
    variants=VARIANTS,
    smoke_variants=("full", "wo_both", "sparse_graph"),
    allowed_methods=("cig_td3",),
)
