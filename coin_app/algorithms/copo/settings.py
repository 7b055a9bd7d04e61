"""CoPO's settings (IPPO's, ``ppo_family/settings.py``, plus the local coordination factors and their meta-gradient) and spec."""

from __future__ import annotations

from dataclasses import dataclass

from coin_app.algorithms.checks import INF, Rule, choice, non_negative, positive
from coin_app.algorithms.choices import LCF_MODES
from coin_app.algorithms.ppo_family.settings import PpoSettings, lifted
from coin_app.algorithms.settings import setting
from coin_app.algorithms.spec import AlgorithmSpec, Capabilities

LCF = "the LCF meta-gradient (copo/learner.py)"
DRAWS = "the envs' LCF draws (adapters/lcf.py)"


@dataclass(frozen=True)
class CopoSettings(PpoSettings):
    """CoPO (Peng et al., NeurIPS 2021): IPPO with LCF-coordinated advantages and an LCF meta-gradient."""

    neighbour_radius: float = setting(
        40.0,
        positive(),
        "neighbour reward: mean reward of the others strictly within this many metres",
        reads="the neighbour value head's reward",
    )
    initial_lcf_mean: float = setting(
        0.0,
        Rule("float", -1.0, 1.0, lo_open=True, hi_open=True),
        "initial mean of the LCF distribution, in (-1, 1) (LCF 0 = selfish, 1 = altruistic)",
        reads=DRAWS,
    )
    initial_lcf_std: float = setting(
        0.1,
        Rule("float", 0.0, 7.0, lo_open=True, hi_open=True),
        "initial std of the LCF distribution",
        reads=DRAWS,
    )
    lcf_lr: float = setting(
        1e-4, positive("float", 1.0), "Adam learning rate of the LCF distribution parameters (meta-gradient)", reads=LCF
    )
    lcf_num_iters: int = setting(
        5, non_negative("int"), "meta-gradient passes over each train batch (0 = fixed LCF distribution)", reads=LCF
    )
    lcf_minibatch_size: int | None = setting(
        None, positive("int", INF, None), "meta-gradient minibatch (agent transitions); None = minibatch_size", reads=LCF
    )
    eval_lcf: str = setting(
        "sampled",
        choice(*LCF_MODES),
        "LCF of each vehicle in evaluate / export / the protocol: 'sampled' = one draw per vehicle from the learned distribution "
        "(CoPO's evaluation), 'mean' = the learned mean for every vehicle",
        reads="the RLModule (copo/rl_module.py)",
    )


PRESETS = lifted(CopoSettings)  # the PPO family's presets

COPO = AlgorithmSpec(
    name="copo",
    description="CoPO: PPO on LCF-coordinated ego/neighbour advantages, LCF meta-gradient",
    build="coin_app.algorithms.copo.copo:build_copo_config",
    # the neighbour and global value heads learn from the other agents' rewards
    capabilities=Capabilities(on_policy=True, centralized_critic=True, joint_replay=False),
    settings=CopoSettings,
    presets=PRESETS,
)
