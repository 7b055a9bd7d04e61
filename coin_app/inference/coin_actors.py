"""The COIN authors' released actors (github.com/marmotlab/COIN, MIT), read with numpy alone.

Each released ``TD3_<scene>_<seed>_best_model_<episode>_<success>_actor`` file is a PyTorch
``state_dict`` (torch's zip format) of the official ``models/coin.py`` ``Actor``: Linear(obs, 256)
→ ReLU → Linear(256, 256) → ReLU → Linear(256, 256) → ReLU → Linear(256, 2) → tanh, keys
``l1.{0,2,4,6}.{weight,bias}``. :func:`read_state_dict` reads such a file without torch (a pickle
reader that accepts only an ordered dict of float tensors, so a file cannot run code), and
:func:`load_coin_actor` returns it as a :class:`~coin_app.inference.numpy_policy.NumpyPolicy`.

The files are not shipped (24 actors, 15 MB): :func:`find_coin_actors` finds them under a local
directory — a copy laid out as ``<scene>/TD3_<scene>_<seed>_..._actor`` or a clone of the COIN
repository (``runs/<scene>/<seed>/model/``) — named by ``--actors`` or ``$COIN_OFFICIAL_ACTORS``.
"""

from __future__ import annotations

import os
import pickle
import re
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.inference.numpy_policy import NumpyPolicy

ACTORS_ENV = "COIN_OFFICIAL_ACTORS"
SOURCE = "github.com/marmotlab/COIN (commit 6f5f4ed), MIT licence, Copyright (c) 2026 MARMot Lab @ NUS-ME"
LAYERS = ("l1.0", "l1.2", "l1.4", "l1.6")
ACTIVATIONS = ("relu", "relu", "relu", "tanh")
_NAME = re.compile(r"TD3_(?P<scene>[a-z]+)_(?P<seed>\d+)_best_model_(?P<episode>\d+)_(?P<success>[0-9.]+)_actor$")
_DTYPES = {"FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16}


def _rebuild_tensor(storage: np.ndarray, offset: int, size: tuple, stride: tuple, *_: Any) -> np.ndarray:
    """torch's ``_rebuild_tensor_v2`` on a numpy storage: the strided view, copied."""
    item = storage.itemsize
    view = np.lib.stride_tricks.as_strided(storage[offset:], shape=tuple(size), strides=tuple(s * item for s in stride))
    return np.array(view)


class _StateDictUnpickler(pickle.Unpickler):
    """Unpickles a torch ``state_dict`` of float tensors into numpy arrays; any other class is refused."""

    def __init__(self, file: Any, archive: zipfile.ZipFile, prefix: str, path: Path):
        super().__init__(file)
        self.archive, self.prefix, self.path = archive, prefix, path

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) == ("collections", "OrderedDict"):
            return OrderedDict
        if (module, name) == ("torch._utils", "_rebuild_tensor_v2"):
            return _rebuild_tensor
        if module == "torch" and name in _DTYPES:
            return _DTYPES[name]
        raise pickle.UnpicklingError(f"{self.path} holds {module}.{name}; allowed: a state_dict of float tensors")

    def persistent_load(self, pid: Any) -> np.ndarray:
        _, dtype, key, _location, numel = pid
        raw = self.archive.read(f"{self.prefix}/data/{key}")
        return np.frombuffer(raw, dtype=np.dtype(dtype).newbyteorder("<"), count=int(numel))


def read_state_dict(path: str | Path) -> dict[str, np.ndarray]:
    """The tensors of a torch ``state_dict`` file (torch's zip format) as numpy arrays, without torch."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as archive:
            pkl = next((n for n in archive.namelist() if n.endswith("/data.pkl")), None)
            if pkl is None:
                raise ValueError(f"{path} is not a torch state_dict file (no data.pkl inside)")
            with archive.open(pkl) as f:
                state = _StateDictUnpickler(f, archive, pkl.rsplit("/", 1)[0], path).load()
    except zipfile.BadZipFile as exc:
        raise ValueError(f"{path} is not a torch state_dict file (torch's zip format): {exc}") from exc
    if not isinstance(state, dict):
        raise ValueError(f"{path} holds a {type(state).__name__}; allowed: a state_dict")
    return dict(state)


def load_coin_actor(path: str | Path) -> NumpyPolicy:
    """One released actor file as a deterministic numpy policy ``(N, obs_dim) -> (N, 2)``; meta: scene, seed, episode, success."""
    path = Path(path)
    state = read_state_dict(path)
    missing = [f"{layer}.{p}" for layer in LAYERS for p in ("weight", "bias") if f"{layer}.{p}" not in state]
    if missing:
        raise ValueError(f"{path} is not a COIN actor: it lacks {', '.join(missing)}")
    weights = [state[f"{layer}.weight"].astype(np.float32) for layer in LAYERS]
    biases = [state[f"{layer}.bias"].astype(np.float32) for layer in LAYERS]
    match = _NAME.search(path.name)
    meta: dict[str, Any] = {"source": SOURCE, "file": path.name}
    if match:
        meta |= {"scene": match["scene"], "seed": int(match["seed"]), "episode": int(match["episode"]), "train_success": match["success"]}
    return NumpyPolicy(weights, biases, list(ACTIVATIONS), meta)


def actors_root(given: str | Path | None) -> Path:
    """The directory of the released actors: ``given``, else ``$COIN_OFFICIAL_ACTORS``; a ValueError if neither names one."""
    root = given if given is not None else os.environ.get(ACTORS_ENV)
    if not root:
        raise ValueError(f"no COIN actors directory: pass --actors DIR or set {ACTORS_ENV} (a clone of github.com/marmotlab/COIN works)")
    path = Path(root).expanduser()
    if not path.is_dir():
        raise ValueError(f"COIN actors directory {path} does not exist; allowed: a directory of the released actors or a COIN clone")
    return path


def find_coin_actors(root: str | Path, scene: str) -> dict[int, Path]:
    """Training seed -> actor file of ``scene`` under ``root`` (``<scene>/`` or a COIN clone's ``runs/<scene>/<seed>/model/``).

    Where a seed has several files (a COIN clone keeps every saved best model), the one with the highest training
    success is taken, ties to the later episode — the file the official ``coin_eval.py`` loads (``load_best``).
    """
    root = Path(root)
    found: dict[int, tuple[tuple[float, int], Path]] = {}
    for base in (root / scene, root / "runs" / scene):
        if not base.is_dir():
            continue
        for path in base.rglob(f"TD3_{scene}_*_actor"):
            match = _NAME.search(path.name)
            if match is None or match["scene"] != scene:
                continue
            key = (float(match["success"]), int(match["episode"]))
            seed = int(match["seed"])
            if seed not in found or key > found[seed][0]:
                found[seed] = (key, path)
    return {seed: found[seed][1] for seed in sorted(found)}
