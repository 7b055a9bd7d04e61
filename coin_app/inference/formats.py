"""Export formats by name and one loader for every exported file (numpy, TorchScript, ONNX, switching pairs).

=============  ========  ==========================  ===========================
format         suffix    loading needs               forward pass
=============  ========  ==========================  ===========================
numpy          ``.npz``  numpy                       numpy matmuls
torchscript    ``.pt``   torch                       scripted torch module
onnx           ``.onnx`` onnxruntime (extra)         onnxruntime CPU, 1 thread
=============  ========  ==========================  ===========================

A ``.json`` file is a switching pair (:mod:`coin_app.inference.switching`) of any of these.
None of the loaders imports Ray.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coin_app.inference.numpy_policy import export_numpy, load_numpy
from coin_app.inference.onnx_policy import export_onnx, load_onnx
from coin_app.inference.shipped import resolve, shipped_policies
from coin_app.inference.switching import load_pair
from coin_app.inference.torchscript_policy import export_torchscript, load_torchscript

# name -> (file suffix, exporter(actor, path, meta), loader(path))
FORMATS: dict[str, tuple[str, Callable[..., Path], Callable[[Path], Any]]] = {
    "numpy": (".npz", export_numpy, load_numpy),
    "torchscript": (".pt", export_torchscript, load_torchscript),
    "onnx": (".onnx", export_onnx, load_onnx),
}


def check_format(fmt: str, path: str | Path) -> None:
    """A ValueError unless ``fmt`` is a known format and ``path`` carries its suffix."""
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; allowed: {', '.join(FORMATS)}")
    suffix = FORMATS[fmt][0]
    if Path(path).suffix != suffix:
        raise ValueError(f"output {path} must end in {suffix} for format {fmt!r} (the loader picks the format by suffix)")


def export_policy(actor: Any, path: str | Path, fmt: str = "numpy", meta: dict[str, Any] | None = None) -> Path:
    """Write a torch actor to ``path`` in format ``fmt``; returns the path.

    Atomic: the file is written to a hidden sibling, flushed to disk, then renamed over ``path``, so a failed
    export (a full disk, a bad actor) leaves an earlier file at ``path`` as it was and no partial file behind.
    """
    check_format(fmt, path)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial{path.suffix}")
    try:
        FORMATS[fmt][1](actor, partial, meta)
        with open(partial, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path


def load_policy(path: str | Path) -> Any:
    """Load a shipped policy by name (``python -m coin_app policies``), an exported actor file (``.npz``, ``.pt``, ``.onnx``)
    or a switching pair (``.json``) as a callable policy ``(N, obs_dim) -> (N, act_dim)``."""
    path = Path(resolve(path))
    if not path.is_file():
        names = ", ".join(shipped_policies())
        raise ValueError(f"policy file {path} does not exist (shipped policies, loaded by name: {names})")
    if path.suffix == ".json":
        return load_pair(path, load_policy)
    for suffix, _, loader in FORMATS.values():
        if path.suffix == suffix:
            return loader(path)
    allowed = ", ".join(f"{s} ({n})" for n, (s, _, _) in FORMATS.items())
    raise ValueError(f"{path} has no known policy suffix; allowed: {allowed}, .json (switching pair)")
