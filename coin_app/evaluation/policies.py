"""One policy interface for evaluation: an RLlib checkpoint, an exported policy file, a switching pair, or a callable.

:func:`as_policy` turns any of them into a policy that
:func:`~coin_app.evaluation.evaluate.evaluate_policy` runs on either backend: a callable
``(N, obs_dim) -> (N, 2)``, or, for CoPO with per-vehicle LCFs, an agent-aware policy
(:class:`~coin_app.sim.rollout.AgentPolicy`). An exported CoPO actor whose metadata holds the
learned LCF distribution (``"lcf"``) takes ``[obs | LCF feature]``; it is wrapped back into the
same per-vehicle draws as its checkpoint (:class:`~coin_app.adapters.lcf.SampledLCFPolicy`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from coin_app.adapters.lcf import with_lcf
from coin_app.algorithms.checkpoint_files import ACTOR_FILE, ACTOR_ONLY, contents_of, read_metadata
from coin_app.algorithms.checkpoints import load_checkpoint_policy
from coin_app.inference import load_policy as load_exported_policy
from coin_app.inference.shipped import resolve
from coin_app.inference.switching import load_pair
from coin_app.sim.rollout import AgentPolicy, Policy


def checkpoint_policy(checkpoint: Path) -> Policy | AgentPolicy:
    """A checkpoint's evaluation policy: its module's deterministic actor (:func:`load_checkpoint_policy`), or an archived
    actor-only copy's exported actor (CoPO's with the same per-vehicle LCF draws)."""
    read_metadata(checkpoint)  # verified first, whichever kind
    if contents_of(checkpoint) == ACTOR_ONLY:
        return with_lcf(load_exported_policy(Path(checkpoint) / ACTOR_FILE))
    return load_checkpoint_policy(Path(checkpoint))


def as_policy(source: Any) -> Policy | AgentPolicy:
    """A batch policy from a callable, a shipped policy's name, a checkpoint directory, an exported ``.npz`` or a pair ``.json``."""
    if callable(source):
        return source
    source = resolve(source)  # a shipped policy's name: its file
    if not isinstance(source, (str, Path)):
        raise TypeError(
            f"cannot make a policy from {type(source).__name__}; allowed: a callable, a checkpoint directory, an exported policy file"
        )
    path = Path(source)
    if path.is_dir():
        return checkpoint_policy(path)
    if path.is_file() and path.suffix == ".json":
        return load_pair(path, as_policy)
    if path.is_file():
        return with_lcf(load_exported_policy(path))
    raise ValueError(
        f"policy source {path} does not exist; allowed: a checkpoint directory or an exported policy file (.npz, .pt, .onnx, .json)"
    )


__all__ = ["AgentPolicy", "Policy", "as_policy", "checkpoint_policy", "with_lcf"]
