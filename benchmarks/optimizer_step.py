"""Time of one Adam step over a TD3-family module's networks: the per-tensor loop, foreach and fused, side by side.

Usage: python benchmarks/optimizer_step.py [--algos cig_td3 itd3 traco] [--steps 200] [--rounds 5]

The learners of CIG-TD3, ITD3 and TraCo step one Adam optimizer per network (actor, local
critics, centralized or domain critic). PyTorch's CPU default is the per-tensor loop, whose
cost is mostly per-tensor overhead for these small networks; the learners use the fused kernel
(``coin_app.algorithms.td3.learner.Td3TorchLearner.register_adam``). For each algorithm
at its quick size (the learning curves, the reduced scale) and at the paper size, this prints the
milliseconds of one step of all its optimizers with each implementation, the ratios to the
per-tensor loop, and the largest parameter difference after ``--steps`` steps from the same
state and gradients (fused rounds differently; foreach does not). The three implementations take
turns in ``--rounds`` rounds, so a change in the machine's load hits all alike. One torch thread.
"""

from __future__ import annotations

import argparse
import os
import time

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import torch  # noqa: E402

from coin_app.algorithms import registry  # noqa: E402
from coin_app.training import fresh_module  # noqa: E402

KINDS: dict[str, dict[str, bool]] = {"per-tensor": {"foreach": False}, "foreach": {"foreach": True}, "fused": {"fused": True}}


def networks(module: torch.nn.Module) -> list[list[torch.nn.Parameter]]:
    """The parameter lists the learner gives one Adam each (the module's trained networks, not its targets)."""
    names = ("actor", "local_q", "central", "domain_q", "baseline")
    nets = [getattr(module, name) for name in names if getattr(module, name, None) is not None]
    return [[p for p in net.parameters() if p.requires_grad] for net in nets]


def time_kinds(groups: list[list[torch.nn.Parameter]], steps: int, rounds: int) -> dict[str, tuple[float, float]]:
    """Per implementation: (ms per step of all optimizers, max |parameter - per-tensor result| after the run)."""
    gen = torch.Generator().manual_seed(0)
    grads = [[torch.randn(p.shape, generator=gen) for p in g] for g in groups]
    state = {}
    for kind, kw in KINDS.items():
        params = [[p.detach().clone().requires_grad_() for p in g] for g in groups]
        for ps, gs in zip(params, grads):
            for p, g in zip(ps, gs):
                p.grad = g.clone()
        state[kind] = (params, [torch.optim.Adam(ps, lr=1e-3, **kw) for ps in params])
    spent = dict.fromkeys(KINDS, 0.0)
    per_round = max(1, steps // rounds)
    for _ in range(rounds):
        for kind, (_, opts) in state.items():
            t0 = time.perf_counter()
            for _ in range(per_round):
                for opt in opts:
                    opt.step()
            spent[kind] += time.perf_counter() - t0
    ref = torch.cat([p.detach().flatten() for g in state["per-tensor"][0] for p in g])
    out = {}
    for kind, (params, _) in state.items():
        flat = torch.cat([p.detach().flatten() for g in params for p in g])
        out[kind] = (1000 * spent[kind] / (per_round * rounds), float((flat - ref).abs().max()))
    return out


def main() -> None:
    """Print the step times, ratios and differences per algorithm and size."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algos", nargs="+", default=["cig_td3", "itd3", "traco"])
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(1)
    print(f"Adam step of all of a learner's optimizers, {args.steps} steps in {args.rounds} alternating rounds, 1 torch thread")
    print("| algorithm | size | tensors | parameters | per-tensor ms | foreach ms | fused ms | fused / per-tensor | fused max diff |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for algo in args.algos:
        for size, overrides in (("quick", registry.quick_settings(algo)), ("paper", {})):
            groups = networks(fresh_module(algo, "intersection", overrides))
            timed = time_kinds(groups, args.steps, args.rounds)
            n_t, n_p = sum(len(g) for g in groups), sum(p.numel() for g in groups for p in g)
            per, fe, fu = (timed[k][0] for k in KINDS)
            print(
                f"| {algo} | {size} | {n_t} | {n_p:,} | {per:.2f} | {fe:.2f} | {fu:.2f} | {fu / per:.2f} | {timed['fused'][1]:.1e} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
