"""A run's checkpoints: their coin_app metadata, atomic saves, and the checks before a resume or into a run directory."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.core.rl_module.rl_module import RLModule

from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import PREVIOUS_SUFFIX, save_checkpoint
from coin_app.sim.scenarios import config_from_dict
from coin_app.training.config import fresh_module


def checkpoint_meta(name: str, scenario: str, seed: int, overrides: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """The coin_app metadata stored with every checkpoint (what evaluation and export read back)."""
    env_cfg, _ = registry.split_overrides(name, overrides, scenario)
    learners = {k: v for k, v in overrides.items() if k in registry.LEARNER_KEYS}  # how it trained, not what a CPU machine rebuilds
    rebuilt = {k: v for k, v in overrides.items() if k not in learners}
    meta = {"algo": name, "scenario": scenario, "seed": seed, "overrides": rebuilt, "env_config": env_cfg}
    return meta | ({"learners": learners} if learners else {}) | extra


def save(algo: Algorithm, checkpoint: Path, meta: dict[str, Any], atomic: bool = True) -> None:
    """Save the algorithm, its coin_app metadata and manifest to ``checkpoint`` (atomically: ``checkpoint_files.save_checkpoint``)."""
    save_checkpoint(algo, checkpoint, meta, atomic=atomic)


def check_resume(checkpoint: Path, meta: dict[str, Any], name: str, scenario: str, overrides: dict[str, Any]) -> None:
    """Refuse to resume ``checkpoint`` (metadata ``meta``) as another algorithm, scenario, scenario config or network shape."""
    if meta.get("algo") != name:
        raise ValueError(f"--resume {checkpoint} was trained by {meta.get('algo')!r}, not {name!r}; allowed: --algo {meta.get('algo')}")
    if meta.get("scenario") != scenario:
        trained = meta.get("scenario")
        raise ValueError(f"--resume {checkpoint} was trained on scenario {trained!r}, not {scenario!r}; allowed: --scenario {trained}")
    spec = registry.get(name)
    # keys the algorithm no longer takes shaped nothing of it (an ITD3 run from before td3/ carries CIG-TD3's unused keys)
    known = set(registry.keys(name)) | set(registry.scenario_keys(scenario))
    old_overrides = {k: v for k, v in meta.get("overrides", {}).items() if k in known}
    old_env, old_algo = registry.split_overrides(name, old_overrides, scenario)
    new_env, _ = registry.split_overrides(name, overrides, scenario)
    old_cfg = config_from_dict(scenario, {**spec.scenario_defaults(old_algo), **old_env})
    new_cfg = config_from_dict(scenario, {**spec.scenario_defaults(dict(overrides)), **new_env})
    if old_cfg != new_cfg:
        diff = sorted(k for k in old_cfg.__dataclass_fields__ if getattr(old_cfg, k) != getattr(new_cfg, k))
        shown = ", ".join(f"{k}={getattr(old_cfg, k)!r} there, {getattr(new_cfg, k)!r} here" for k in diff[:4])
        raise ValueError(
            f"--resume {checkpoint} was trained on another {scenario} config ({shown}); allowed: the checkpoint's --set values"
        )
    seed = int(meta.get("seed", 0))
    old_shapes = _parameter_shapes(fresh_module(name, scenario, old_overrides, seed))
    new_shapes = _parameter_shapes(fresh_module(name, scenario, dict(overrides), seed))
    if old_shapes != new_shapes:
        diff = sorted(k for k in old_shapes.keys() | new_shapes.keys() if old_shapes.get(k) != new_shapes.get(k))
        k = diff[0]
        raise ValueError(
            f"--resume {checkpoint} has another network shape ({k}: {old_shapes.get(k)} there, {new_shapes.get(k)} here; "
            f"{len(diff)} parameter(s) differ); allowed: the checkpoint's --set values {old_overrides}"
        )


def _parameter_shapes(module: RLModule) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every parameter and buffer of a module."""
    return {k: tuple(v.shape) for k, v in module.state_dict().items() if hasattr(v, "shape")}


def check_run_dir(out: Path, resume: Path | None, overwrite: bool) -> None:
    """Refuse ``out`` if it holds an earlier run (unless resumed or overwritten) or cannot be written; before any work."""
    earlier = [p for p in (out / "checkpoint", out / ("checkpoint" + PREVIOUS_SUFFIX), out / "summary.json") if p.exists()]
    if earlier and resume is None and not overwrite:
        raise ValueError(
            f"{out} holds an earlier run ({earlier[0].name}); allowed: --resume {out / 'checkpoint'} to continue it, "
            "--overwrite to replace it, or another --out"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".coin_app_write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"cannot write the run directory {out}: {exc.strerror or exc}; allowed: a writable path for --out") from exc
