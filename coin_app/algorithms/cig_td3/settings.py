"""CIG-TD3's settings (ITD3's, ``td3/settings.py``, plus the centralized critic and its ablation switches), presets and spec."""

from __future__ import annotations

from dataclasses import dataclass, replace

from coin_app.algorithms.checks import BOOL, INF, choice, non_negative, positive
from coin_app.algorithms.choices import GAT_INITS, GLOBAL_MODULES, LOCAL_MODULES
from coin_app.algorithms.settings import redeclare, setting
from coin_app.algorithms.spec import AlgorithmSpec
from coin_app.algorithms.td3.settings import CAPABILITIES, OPTIM, SMALL_PRESETS, Td3Settings
from coin_app.algorithms.td3.settings import PRESETS as TD3_PRESETS

CRITIC = "the centralized critic (cig_td3/critic.py)"
LOSS = "CIG-TD3's losses (cig_td3/losses.py)"


@dataclass(frozen=True)
class CigTd3Settings(Td3Settings):
    """COIN's CIG-TD3: ITD3 plus the interaction-aware centralized critic (CVAE pair latents, a GAT) and the counterfactual baseline."""

    critic_lr: float = redeclare(Td3Settings, "critic_lr", 3e-4, "Adam learning rate of the twin local critics")
    tau: float = redeclare(Td3Settings, "tau", 0.005, "soft target update rate of actor, local and global critics")
    hidden: int = redeclare(Td3Settings, "hidden", 256, "width of actor, local-critic and CVAE layers")
    precision: str = redeclare(
        Td3Settings,
        "precision",
        "auto",
        "learner update precision: auto | bf16 | fp32 (bf16: every loss forward pass under torch.autocast bfloat16; parameters, "
        "optimizer state, TD targets, loss reductions and soft updates stay fp32; 0.37x the fp32 update time at the paper's "
        "sizes on a CPU with bf16, 10x on one without, no loss of success at equal env steps: "
        "docs/studies/learning_curves_precision; auto: bf16 where the learner's device multiplies bf16 natively, a CUDA GPU "
        "with bf16 or a CPU with oneDNN bf16, else fp32)",
    )
    central_critic_lr: float = setting(
        3e-4,
        positive("float", 1.0),
        "Adam learning rate of the centralized critic: twin global Q, baseline V and CVAE",
        reads=OPTIM,
        official=2e-4,
    )
    global_critic: bool = setting(True, BOOL, "use the centralized critic (False: TD3's losses only; ITD3 is --algo itd3)", reads=LOSS)
    counterfactual_baseline: bool = setting(True, BOOL, "subtract the counterfactual baseline V in the actor loss (Eq. 12)", reads=LOSS)
    local_module: str = setting(
        "cvae", choice(*LOCAL_MODULES), "pairwise interaction module: cvae | attention (Table B.1) | none (w/o VAE)", reads=CRITIC
    )
    global_module: str = setting(
        "gat", choice(*GLOBAL_MODULES), "global interaction module: gat | gcn | graphsage | none (w/o GAT: mean-pool)", reads=CRITIC
    )
    graph: float | str = setting(
        "full", positive("float", INF, "full"), "'full' graph, or a radius in metres for a sparse graph (Tables B.2/B.3: 40)", reads=CRITIC
    )
    global_weight: float = setting(1.0, non_negative(), "weight of the global term in the actor loss (paper 1.0)", reads=LOSS, official=0.8)
    vae_weight: float = setting(1.0, non_negative(), "weight of the CVAE loss in the centralized-critic loss", reads=LOSS, official=0.01)
    kl_beta: float = setting(1.0, non_negative(), "weight of the KL term inside the CVAE loss", reads=LOSS)
    latent_dim: int = setting(20, positive("int"), "CVAE latent size", reads=CRITIC)
    node_width: int = setting(128, positive("int"), "GAT node feature width", reads=CRITIC)
    gat_heads: int = setting(
        2,
        positive("int"),
        "heads of the first GAT layer, concatenated (official code 2; the paper is silent; 1 before coin_app 0.2)",
        reads=CRITIC,
    )
    gat_init: str = setting(
        "xavier",
        choice(*GAT_INITS),
        "GAT weight initialization: xavier (gain 1.414, official code) | default (torch Linear, before 0.2)",
        reads=CRITIC,
    )


def _presets() -> dict[str, CigTd3Settings]:
    """The TD3 family's presets with the centralized critic's widths and rate; the small presets in fp32 like their family."""
    out = {name: CigTd3Settings.lift(value) for name, value in TD3_PRESETS.items()}
    small = {"latent_dim": 8, "node_width": 16, "central_critic_lr": 1e-3}
    for name in SMALL_PRESETS:
        # fp32: bf16 does not pay at these widths (3.3x the fp32 update on a CPU without bf16, 1.0-1.4x on one with AMX)
        out[name] = replace(out[name], **small, precision="fp32")
    out["tiny"] = replace(out["tiny"], latent_dim=4, node_width=8)
    return out


PRESETS = _presets()

CIG_TD3 = AlgorithmSpec(
    name="cig_td3",
    description="COIN: CIG-TD3 with the interaction-aware centralized critic",
    build="coin_app.algorithms.cig_td3.cig_td3:build_cig_td3_config",
    capabilities=replace(CAPABILITIES, centralized_critic=True),
    settings=CigTd3Settings,
    presets=PRESETS,
)
