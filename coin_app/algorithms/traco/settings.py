"""TraCo's settings (ITD3's, ``td3/settings.py``, plus its domain critic; every choice nobody published is marked "inference"),
presets and spec."""

from __future__ import annotations

from dataclasses import dataclass, replace

from coin_app.algorithms.checks import BOOL, choice, non_negative, positive
from coin_app.algorithms.choices import DOMAIN_REWARDS, NEIGHBOUR_FEATURES
from coin_app.algorithms.settings import redeclare, setting
from coin_app.algorithms.spec import AlgorithmSpec
from coin_app.algorithms.td3.settings import CAPABILITIES, OPTIM, SMALL_PRESETS, Td3Settings
from coin_app.algorithms.td3.settings import PRESETS as TD3_PRESETS

CRITIC = "the domain critic (traco/networks.py)"
LOSS = "TraCo's losses (traco/losses.py)"


@dataclass(frozen=True)
class TracoSettings(Td3Settings):
    """TraCo (Liu et al., CoRL 2023) as COIN ran it (COIN §5.2): TD3 with a cross-attention domain critic within 40 m."""

    critic_lr: float = redeclare(
        Td3Settings, "critic_lr", 3e-4, "Adam learning rate of the twin domain critic (and of the individual critic, if any)"
    )
    tau: float = redeclare(
        Td3Settings, "tau", 0.005, "soft target update rate of the actor and the domain critic (and of the individual critic, if any)"
    )
    hidden: int = redeclare(
        Td3Settings, "hidden", 256, "width of the actor's layers, of the attention tokens and of the critic heads (COIN's TD3 hidden size)"
    )
    baseline_lr: float = setting(
        3e-4, positive("float", 1.0), "Adam learning rate of the counterfactual baseline (inference: COIN's critic rate)", reads=OPTIM
    )
    domain_radius: float = setting(
        40.0,
        positive(),
        "metres: the ego's domain, the others strictly within it (COIN §5.2: 40 m; CoPO's neighbours_distance)",
        reads=CRITIC,
    )
    domain_reward: str = setting(
        "mean",
        choice(*DOMAIN_REWARDS),
        "inference: the domain critic's reward, mean over the ego and its domain | neighbours (mean over the domain, "
        "0 if empty: CoPO's nei_rewards) | own (the ego's reward)",
        reads=LOSS,
    )
    attention_heads: int = setting(
        4, positive("int"), "inference: heads of the cross-attention (the width is hidden, split over the heads)", reads=CRITIC
    )
    token_layers: int = setting(
        2, positive("int"), "inference: layers of the ego-token MLP([o_i, a_i]) and of the neighbour-token MLP", reads=CRITIC
    )
    neighbour_features: str = setting(
        "relative+absolute",
        choice(*NEIGHBOUR_FEATURES),
        "inference: neighbour token inputs [s_j - s_i, s_j, a_j] | absolute ([s_j, a_j], COIN style) | relative ([s_j - s_i, a_j])",
        reads=CRITIC,
    )
    null_token: bool = setting(
        True,
        BOOL,
        "inference: a learned, always attendable null token (False: a fixed zero token) so an empty domain is defined",
        reads=CRITIC,
    )
    counterfactual_baseline: bool = setting(
        True,
        BOOL,
        "inference: train the baseline b (the domain critic with the ego action set to (-1, -1), COIN's released-code "
        "convention) and subtract it in the actor loss; it carries no actor gradient (logged as the advantage)",
        reads=LOSS,
    )
    individual_critic: bool = setting(
        False, BOOL, "inference: also a twin individual critic on the ego's reward, its Q^l_1 added to the actor objective", reads=LOSS
    )
    domain_weight: float = setting(1.0, non_negative(), "weight w of the domain term Q^D_1 - b in the actor objective", reads=LOSS)


def _presets() -> dict[str, TracoSettings]:
    """The TD3 family's presets; the baseline at the critics' rate where they change it. The reduced protocol adds the optional
    individual critic: with the domain critic alone TraCo collapsed at once to one braking action on seeds 0 and 1 under the
    protocol's guard, with it both seeds drove (docs/results/journal.md); the dense protocol keeps that guard, and the critic."""
    out = {name: TracoSettings.lift(value) for name, value in TD3_PRESETS.items()}
    for name in SMALL_PRESETS:
        out[name] = replace(out[name], baseline_lr=out[name].critic_lr)
    for name in ("reduced", "dense"):
        out[name] = replace(out[name], individual_critic=True)
    return out


PRESETS = _presets()

TRACO = AlgorithmSpec(
    name="traco",
    description="TraCo (re-implemented, TD3, per COIN §5.2): cross-attention domain critic, counterfactual advantage within 40 m",
    build="coin_app.algorithms.traco.traco:build_traco_config",
    capabilities=replace(CAPABILITIES, centralized_critic=True),
    settings=TracoSettings,
    presets=PRESETS,
)
