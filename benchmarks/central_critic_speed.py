"""Forward + backward time of the COIN centralized critic (twin Q + V + CVAE loss) on one CPU thread.

Usage: python benchmarks/central_critic_speed.py [--batch 256] [--others 29 47] [--repeats 5] [--occupancy 1.0 0.65]
       [--gat 2:xavier 1:default]

For each number N of other-agent slots and each occupancy (fraction of the N slots holding a
real agent; 1.0 = every slot valid, the worst case), times one ``CentralCritic.forward`` with a
CVAE target plus ``backward`` of the summed losses (twin Q + V + CVAE), and the same through the
separate ``q_values`` / ``baseline`` / ``cvae_loss`` calls; prints the median of ``--repeats``
runs (after one warm-up run). Default config: paper widths, CVAE + GAT, full graph, obs_dim 91.
``--gat HEADS:INIT ...`` times one critic per GAT variant side by side (``gat_heads`` /
``gat_init`` of ``CentralCriticConfig``; ``1:default`` is the single-head GAT used before issue
#27, ``2:xavier`` the official code's first layer, the default; ``docs/decisions.md`` §2).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import torch  # noqa: E402

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig  # noqa: E402


def time_update(
    critic: CentralCritic, batch: int, others: int, occupancy: float, repeats: int, separate: bool = False, seed: int = 0
) -> float:
    """Median seconds of forward (q1, q2, V, CVAE terms) + backward over ``repeats`` runs.

    ``separate``: call ``q_values``, ``baseline`` and ``cvae_loss`` one by one (the encoder runs
    twice) instead of the single ``forward`` pass.
    """
    cfg = critic.cfg
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, cfg.obs_dim, generator=g)
    state = torch.randn(batch, cfg.state_dim, generator=g)
    action = torch.rand(batch, cfg.act_dim, generator=g) * 2 - 1
    others_state = torch.randn(batch, others, cfg.state_dim, generator=g)
    others_action = torch.rand(batch, others, cfg.act_dim, generator=g) * 2 - 1
    others_mask = torch.rand(batch, others, generator=g) < occupancy
    target_y = torch.randn(batch, cfg.obs_dim + cfg.state_dim + 1, generator=g)
    times = []
    for k in range(repeats + 1):
        critic.zero_grad(set_to_none=True)
        t0 = time.perf_counter()
        if separate:
            q1, q2 = critic.q_values(obs, state, action, others_state, others_action, others_mask)
            v = critic.baseline(obs, state, others_state, others_action, others_mask)
            recon, kl = critic.cvae_loss(obs, state, action, others_state, others_action, others_mask, target_y, g)
        else:
            q1, q2, v, recon, kl = critic(obs, state, action, others_state, others_action, others_mask, target_y, g)
        loss = q1.square().mean() + q2.square().mean() + v.square().mean() + recon + kl
        loss.backward()
        if k > 0:  # the first run is a warm-up
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    """Time the critic for every number of other slots and occupancy and print a table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--others", type=int, nargs="+", default=[29, 47])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--occupancy", type=float, nargs="+", default=[1.0, 0.65])
    parser.add_argument("--local", default="cvae")
    parser.add_argument("--global-module", default="gat")
    parser.add_argument("--encoder-layers", type=int, default=3, help="CVAE encoder hidden layers (default as the official code)")
    parser.add_argument("--decoder-layers", type=int, default=2, help="CVAE decoder hidden layers (default as the official code)")
    parser.add_argument("--gat", nargs="+", default=["2:xavier"], help="GAT variants HEADS:INIT to compare, e.g. 2:xavier 1:default")
    args = parser.parse_args()
    torch.set_num_threads(1)
    critics = {}
    for spec in args.gat:
        heads, _, init = spec.partition(":")
        torch.manual_seed(0)
        cfg = CentralCriticConfig(
            obs_dim=91,
            local_module=args.local,
            global_module=args.global_module,
            cvae_encoder_layers=args.encoder_layers,
            cvae_decoder_layers=args.decoder_layers,
            gat_heads=int(heads),
            gat_init=init or "xavier",
        )
        critics[spec] = critic = CentralCritic(cfg)
        n_params = sum(p.numel() for p in critic.parameters())
        print(
            f"CentralCritic local={args.local} (enc {args.encoder_layers} / dec {args.decoder_layers} hidden layers) "
            f"global={args.global_module} gat={spec}: {n_params} parameters, 1 thread, batch {args.batch}"
        )
    print(f"{'N others':>8} {'occupancy':>9} {'gat':>10} {'one pass: forward (s)':>22} {'separate calls (s)':>19}")
    for n in args.others:
        for occ in args.occupancy:
            for spec, critic in critics.items():
                t = time_update(critic, args.batch, n, occ, args.repeats)
                t_sep = time_update(critic, args.batch, n, occ, args.repeats, separate=True)
                print(f"{n:>8} {occ:>9.2f} {spec:>10} {t:>22.3f} {t_sep:>19.3f}")


if __name__ == "__main__":
    main()
