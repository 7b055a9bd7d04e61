"""A run's checkpoints: their coin_app metadata, atomic saves, and the checks before a resume or into a run directory."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.core.rl_module.rl_module import RLModule

from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import PARTIAL_SUFFIX, PREVIOUS_SUFFIX, SHAPES_KEY, save_checkpoint, shape_difference
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.evaluation.outputs import within
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
    new_shapes = _parameter_shapes(fresh_module(name, scenario, dict(overrides), seed))
    if SHAPES_KEY in meta:  # the shapes as saved: a default changed in the code since is seen too
        old_shapes = recorded_shapes(meta, new_shapes)
    else:  # a checkpoint from before the shapes were recorded: rebuilt from its settings
        old_shapes = _parameter_shapes(fresh_module(name, scenario, old_overrides, seed))
    differ = shape_difference(old_shapes, new_shapes)
    if differ:
        raise ValueError(
            f"--resume {checkpoint} has another network shape ({differ}); allowed: the checkpoint's --set values {old_overrides}"
        )


def _parameter_shapes(module: RLModule) -> dict[str, tuple[int, ...]]:
    """Name -> shape of every parameter and buffer of a module."""
    return {k: tuple(v.shape) for k, v in module.state_dict().items() if hasattr(v, "shape")}


def recorded_shapes(meta: dict[str, Any], here: dict[str, tuple[int, ...]]) -> dict[str, tuple[int, ...]]:
    """The shapes a checkpoint's metadata records, for the tensors a module built here has (a learner's module also
    holds target networks, copies of its networks that a freshly built module creates later)."""
    saved = {k: tuple(v) for k, v in meta[SHAPES_KEY].items()}
    return {k: saved[k] for k in here if k in saved} | {k: v for k, v in saved.items() if k not in here and "target" not in k}


def check_restorable(algo: Algorithm, checkpoint: Path, meta: dict[str, Any], hint: str) -> None:
    """Refuse to restore ``checkpoint`` into ``algo`` when the network its metadata records is not the one ``algo`` built."""
    if SHAPES_KEY not in meta:
        return
    learner = getattr(algo.learner_group, "_learner", None)  # the full module (an env runner's may hold the actor only)
    module = learner.module[SHARED_MODULE_ID] if learner is not None else algo.get_module(SHARED_MODULE_ID)
    if module is None:
        return
    here = _parameter_shapes(module)
    saved = recorded_shapes(meta, here)
    if learner is None:  # an env runner's module may hold the actor only: compare the tensors it has
        saved = {k: v for k, v in saved.items() if k in here}
    differ = shape_difference(saved, here, "in the checkpoint", "in this code")
    if differ:
        raise ValueError(f"checkpoint {checkpoint} holds another network than this code builds ({differ}); allowed: {hint}")


RUN_FILES = ("checkpoint", "checkpoint" + PREVIOUS_SUFFIX, ".checkpoint" + PARTIAL_SUFFIX, "summary.json", "config.json", "tensorboard",
             "ray.log")  # fmt: skip  # what train writes into --out: what --overwrite deletes (nothing else there)


def check_run_dir(out: Path, resume: Path | None, overwrite: bool) -> None:
    """Refuse ``out`` if it holds another run (unless overwritten, or ``resume`` is that run's own checkpoint) or cannot be
    written; ``overwrite`` together with a ``resume`` inside ``out`` is refused (it would delete what it resumes). Before any work."""
    in_place = resume is not None and within(resume, out)
    if overwrite and in_place:
        raise ValueError(
            f"--overwrite would delete {resume}, the checkpoint --resume reads; allowed: --resume {resume} without --overwrite "
            f"(the run goes on in {out}), or another --out"
        )
    earlier = [p for p in (out / "checkpoint", out / ("checkpoint" + PREVIOUS_SUFFIX), out / "summary.json") if p.exists()]
    if earlier and not overwrite and not in_place:
        how = f"--resume {resume} would write over it" if resume is not None else "a fresh run would write over it"
        raise ValueError(
            f"{out} holds an earlier run ({earlier[0].name}); {how}; allowed: --resume {out / 'checkpoint'} to continue that run, "
            "--overwrite to replace it, or another --out"
        )
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".coin_app_write_test"
        probe.write_text("")
        probe.unlink()
    except OSError as exc:
        raise ValueError(f"cannot write the run directory {out}: {exc.strerror or exc}; allowed: a writable path for --out") from exc


def clear_run(out: Path) -> list[str]:
    """Delete an earlier run's files from ``out`` (``RUN_FILES``: checkpoints, summary, config, TensorBoard events, Ray log),
    each renamed aside first so a kill never leaves half of one; the names deleted. Other files in ``out`` stay."""
    removed = []
    for name in RUN_FILES:
        path = out / name
        if not path.exists() and not path.is_symlink():
            continue
        aside = out / f".{name}.deleting-{os.getpid()}"
        os.replace(path, aside)
        if aside.is_dir() and not aside.is_symlink():
            shutil.rmtree(aside)
        else:
            aside.unlink()
        removed.append(name)
    return removed
