"""A trace of the TD3 family's learners: 50 updates of CIG-TD3, ITD3 and TraCo on a fixed seeded batch stream.

Each case builds its learner through the public config path (``training.build_config``, seed 0, torch seeded),
feeds it 50 synthetic batches (numpy, seeded per update; the env-step count grows so that the warm-up, the actor's
start and the learning-rate decay all happen inside the trace) and records every logged loss at every update, the
update counter, the learning rates, and a sha256 plus a few raw values of every tensor of the module (targets
included) and of every optimizer state after the 50 updates. The committed trace (``td3_family_trace.json``) is
what ``tests/test_td3_family_trace.py`` compares against; the refactor of issue 54 was checked bit for bit with it.

    PYTHONPATH=. python tests/td3_family_trace.py --out trace.json [--dump tensors.pt]   # record (dump: every tensor in full)
    PYTHONPATH=. python tests/td3_family_trace.py --compare old.pt new.pt                # max |diff| of losses and tensors
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import torch
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

from coin_app.adapters.rllib_env import CoinMultiAgentEnv
from coin_app.training import build_config

TRACE = Path(__file__).with_name("td3_family_trace.json")
UPDATES = 50
SCENARIO = "bottleneck"
SMALL_SCENARIO = {"num_agents": 3, "horizon": 40, "max_agent_steps": 40}
# every case: small networks, policy delay 3, fast targets, the actor starting after 10 updates, rates decaying from
# update 13 on, the reduced protocol's saturation guard
TD3: dict[str, Any] = {
    "hidden": 16,
    "train_batch_size_per_learner": 16,
    "policy_delay": 3,
    "tau": 0.3,  # far from TD3's 0.005, so that the targets' schedule and order show in the losses within 50 updates
    "warmup_steps": 100,
    "actor_start_steps": 40,
    "lr_decay_start": 150,
    "lr_decay_steps": 200,
    "lr_final_fraction": 0.1,
    "actor_preact_penalty": 0.01,
    "actor_preact_threshold": 1.0,
}
CIG = {"latent_dim": 4, "node_width": 8}
CASES: dict[str, tuple[str, dict[str, Any]]] = {
    "cig_td3": ("cig_td3", {**TD3, **CIG, "precision": "bf16"}),  # the paper preset's on a device with native bf16
    "cig_td3_joint_fp32": ("cig_td3", {**TD3, **CIG, "update_order": "joint", "precision": "fp32", "timeout_bootstrap": False}),
    "itd3": ("itd3", dict(TD3)),
    "traco": ("traco", dict(TD3)),
    "traco_individual": ("traco", {**TD3, "individual_critic": True}),
}


def env_steps(update: int) -> int:
    """The lifetime env-step count handed to update ``update`` (0-based)."""
    return 100 + 4 * update


def batch(cfg: Any, update: int) -> dict[str, np.ndarray]:
    """The seeded synthetic batch of update ``update``: the columns of the joint-step replay, others within about 60 m."""
    scen = cfg.scenario_config()
    b, n, o, s, a = cfg.train_batch_size_per_learner, cfg.max_others, scen.obs_dim, 10, 2
    rng = np.random.default_rng(1000 + update)
    f = np.float32

    def normal(*shape: int, scale: float = 1.0) -> np.ndarray:
        return (rng.standard_normal(shape) * scale).astype(f)

    mask, next_mask = rng.random((b, n)) < 0.6, rng.random((b, n)) < 0.6
    return {
        "obs": rng.random((b, o), dtype=f),
        "state": normal(b, s, scale=0.05),
        "actions": rng.uniform(-1, 1, (b, a)).astype(f),
        "rewards": normal(b),
        "global_rewards": normal(b),
        "terminateds": rng.random(b) < 0.2,
        "truncateds": rng.random(b) < 0.1,
        "new_obs": rng.random((b, o), dtype=f),
        "new_state": normal(b, s, scale=0.05),
        "others_state": normal(b, n, s, scale=0.2) * mask[..., None],
        "others_actions": rng.uniform(-1, 1, (b, n, a)).astype(f) * mask[..., None],
        "others_rewards": normal(b, n) * mask,
        "others_mask": mask,
        "next_others_state": normal(b, n, s, scale=0.2) * next_mask[..., None],
        "next_others_obs": rng.random((b, n, o), dtype=f) * next_mask[..., None],
        "next_others_mask": next_mask,
    }


def _value(v: Any) -> float:
    """A logged metric as a float."""
    return float(v.peek()) if hasattr(v, "peek") else float(v)


def _tensors(learner: Any) -> dict[str, torch.Tensor]:
    """Every tensor of the shared module (targets included) and of every optimizer's state, by a stable name."""
    module = learner.module["shared"].unwrapped()
    out = {f"module.{k}": v.detach().cpu() for k, v in module.state_dict().items()}
    for name, optim in sorted(learner._named_optimizers.items()):
        params = [p for group in optim.param_groups for p in group["params"]]
        for i, p in enumerate(params):
            for key, v in sorted(optim.state.get(p, {}).items()):
                if torch.is_tensor(v):
                    out[f"optim.{name}.{i}.{key}"] = v.detach().cpu()
    return out


def _bytes(t: torch.Tensor) -> bytes:
    """A CPU tensor's raw bytes (bf16 through int16, which numpy lacks)."""
    t = t.contiguous()
    return (t.view(torch.int16) if t.dtype == torch.bfloat16 else t).numpy().tobytes()


def _sha(t: torch.Tensor) -> str:
    """sha256 of a tensor's dtype, shape and bytes."""
    return hashlib.sha256(f"{t.dtype}|{tuple(t.shape)}|".encode() + _bytes(t)).hexdigest()


def _raw_value_keys(tensors: dict[str, torch.Tensor]) -> list[str]:
    """The tensors whose first values the trace keeps verbatim: each network's first weight (targets included)."""
    firsts: dict[str, str] = {}
    for k in tensors:
        if k.startswith("module.") and k.endswith("weight"):
            firsts.setdefault(k.split(".")[1], k)
    return sorted(firsts.values())


def run_case(algo: str, settings: dict[str, Any]) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
    """(the trace of one case, its tensors after the updates, with its losses as tensors under "loss.<update>.<key>")."""
    torch.manual_seed(0)
    cfg = build_config(algo, SCENARIO, {**SMALL_SCENARIO, **settings}, 0)
    torch.manual_seed(0)
    learner = cfg.build_learner(env=CoinMultiAgentEnv(cfg.env_config))
    losses: list[dict[str, str]] = []
    for i in range(UPDATES):
        cols = batch(cfg, i)
        res = learner.update(
            batch=MultiAgentBatch({"shared": SampleBatch(cols)}, env_steps=len(cols["obs"])),
            timesteps={"num_env_steps_sampled_lifetime": env_steps(i)},
        )
        shared = res["shared"]
        losses.append({k: _value(shared[k]).hex() for k in sorted(shared) if k.endswith("loss")})
    tensors = _tensors(learner)
    rates = {name: optim.param_groups[0]["lr"] for name, optim in sorted(learner._named_optimizers.items())}
    optim_sha: dict[str, Any] = {}
    for k, v in tensors.items():  # one sha256 per optimizer over its state tensors in order
        if k.startswith("optim."):
            optim_sha.setdefault(k.split(".")[1], hashlib.sha256()).update(_sha(v).encode())
    trace = {
        "algo": algo,
        "settings": settings,
        "num_updates": int(learner.num_updates),
        "losses": losses,
        "lr": {k: float(v).hex() for k, v in rates.items()},
        "sha256": {k: _sha(v) for k, v in tensors.items() if k.startswith("module.")},
        "optimizer_sha256": {k: h.hexdigest() for k, h in optim_sha.items()},
        "first_values": {k: [float(x).hex() for x in tensors[k].reshape(-1)[:3].tolist()] for k in _raw_value_keys(tensors)},
    }
    for i, row in enumerate(losses):
        for k, v in row.items():
            tensors[f"loss.{i}.{k}"] = torch.tensor(float.fromhex(v), dtype=torch.float64)
    return trace, tensors


def cpu_model() -> str:
    """The processor's vendor, family, model and stepping (``/proc/cpuinfo``; "" where it is not there): two processors
    with the same SIMD capability can still block their matrix products otherwise (two AVX2 AMD EPYCs did)."""
    try:
        lines = Path("/proc/cpuinfo").read_text().split("\n\n")[0].splitlines()
    except OSError:
        return ""
    info = {k.strip(): v.strip() for k, _, v in (line.partition(":") for line in lines)}
    return " ".join(info.get(k, "?") for k in ("vendor_id", "cpu family", "model", "stepping"))


def record(cases: list[str] | None = None) -> tuple[dict[str, Any], dict[str, dict[str, torch.Tensor]]]:
    """The trace of every case (or of ``cases``) and their tensors."""
    torch.set_num_threads(1)
    traces, tensors = {}, {}
    for name in cases or CASES:
        algo, settings = CASES[name]
        traces[name], tensors[name] = run_case(algo, settings)
    meta = {"cpu_capability": torch.backends.cpu.get_cpu_capability(), "cpu": cpu_model(), "torch": torch.__version__, "updates": UPDATES}
    return {"meta": meta, "cases": traces}, tensors


def _same_bits(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Whether two tensors hold the same bits (a NaN matches the same NaN: a loss not logged in that update)."""
    return a.dtype == b.dtype and a.shape == b.shape and _bytes(a) == _bytes(b)


def compare(a: dict[str, dict[str, torch.Tensor]], b: dict[str, dict[str, torch.Tensor]]) -> dict[str, dict[str, float]]:
    """Per case: the max |diff| over the losses and over the tensors, and the names present on one side only."""
    out = {}
    for case in sorted(set(a) | set(b)):
        ta, tb = a.get(case, {}), b.get(case, {})
        common = sorted(set(ta) & set(tb))
        diffs = {k: float((ta[k].double() - tb[k].double()).abs().nan_to_num(0.0).max()) if ta[k].numel() else 0.0 for k in common}
        out[case] = {
            "max_abs_diff_losses": max((v for k, v in diffs.items() if k.startswith("loss.")), default=float("nan")),
            "max_abs_diff_tensors": max((v for k, v in diffs.items() if not k.startswith("loss.")), default=float("nan")),
            "bitwise_equal": all(_same_bits(ta[k], tb[k]) for k in common),
            "only_one_side": sorted(set(ta) ^ set(tb)),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    """Record a trace (JSON, optionally every tensor), or compare two dumps."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, help="the trace as JSON")
    parser.add_argument("--dump", type=Path, help="every tensor and loss in full (torch.save)")
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES))
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"), help="two --dump files: their max |diff|")
    args = parser.parse_args(argv)
    if args.compare:
        print(json.dumps(compare(*(torch.load(p) for p in args.compare)), indent=1))
        return 0
    trace, tensors = record(args.cases)
    if args.out:
        args.out.write_text(json.dumps(trace, indent=1, sort_keys=True) + "\n")
    if args.dump:
        torch.save(tensors, args.dump)
    if not args.out and not args.dump:
        json.dump(trace, sys.stdout, indent=1, sort_keys=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
