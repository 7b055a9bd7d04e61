"""The named choices of algorithm keys, in one module that imports only the scene names (networks, configs and ``checks`` import it)."""

from __future__ import annotations

from coin_app.sim.scenes import ARENA  # noqa: F401  (the second paper's scenario, nav_ppo's; re-exported for the name tables)

# the trainable algorithms, in the registry's order (coin_app.algorithms.registry checks its table against this)
ALGORITHM_NAMES = ("cig_td3", "itd3", "traco", "ippo", "cppo", "mfpo", "copo", "nav_ppo")

LOCAL_MODULES = ("cvae", "attention", "none")  # CIG-TD3's pairwise (local) module of the global critic
GLOBAL_MODULES = ("gat", "gcn", "graphsage", "none")  # CIG-TD3's graph (global) module
GAT_INITS = ("xavier", "default")  # the first GAT layer's initialization: the official code's Xavier (gain 1.414) or torch's
UPDATE_ORDERS = ("critic_first", "joint")  # TD3 family: critics first, then the actor on the updated critics; or one joint step
PRECISIONS = ("fp32", "bf16")  # the learner's update precision
# TD3 family: those, or "auto" = bf16 where the learner's device multiplies bf16 natively, else fp32 (td3/learner.py)
TD3_PRECISIONS = ("auto", *PRECISIONS)
KL_SIGNALS = ("epoch_mean", "last_minibatch")  # PPO: which KL drives the adaptive KL coefficient
WEIGHT_INITS = ("normc", "torch")  # PPO family: RLlib's normc initialization or torch's default
LCF_MODES = ("sampled", "mean")  # how evaluation gives each vehicle its LCF (CoordinatedActorModule.evaluation_lcf)
# nav_ppo's warm start: from scratch (the paper) or a scripted driver's clone
NAV_WARM_STARTS = ("none", "heuristic", "avoiding", "planning")
DOMAIN_REWARDS = ("mean", "neighbours", "own")  # TraCo's domain reward: mean over ego + domain, over the domain only, own
NEIGHBOUR_FEATURES = (
    "relative+absolute",
    "absolute",
    "relative",
)  # TraCo's neighbour tokens: [s_j - s_i, s_j, a_j], [s_j, a_j], [s_j - s_i, a_j]
