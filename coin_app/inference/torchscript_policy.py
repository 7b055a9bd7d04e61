"""The TorchScript export format: the actor as a scripted torch module (``.pt``), loadable without Ray.

The file is ``torch.jit.save`` of the scripted actor with one extra file, ``coin_app.json``:
``{"format": "coin_app.torchscript.v1", "obs_dim": ..., "meta": {...}}``. Loading needs
torch (not Ray, not coin_app's training code); C++ can load it with ``torch::jit::load``.
PyTorch 2.13 marks TorchScript deprecated; its deprecation warnings are silenced here.
"""

from __future__ import annotations

import io
import json
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.inference.layers import ExportedPolicy

FORMAT = "coin_app.torchscript.v1"
EXTRA = "coin_app.json"


class TorchScriptPolicy(ExportedPolicy):
    """A scripted actor ``(N, obs_dim) -> (N, act_dim)`` run under ``torch.inference_mode``."""

    format_name = "torchscript"

    def __init__(self, module: Any, obs_dim: int, meta: dict[str, Any] | None = None):
        super().__init__(obs_dim, meta)
        self.module = module

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, act_dim) for observations (N, obs_dim)."""
        import torch  # optional: inference stays importable without torch (numpy and ONNX policies need none)

        with torch.inference_mode():
            return self.module(torch.from_numpy(self.batch(obs))).numpy()


def export_torchscript(actor: Any, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write a torch actor to ``path`` as TorchScript; returns the path."""
    import torch  # optional: inference stays importable without torch (numpy and ONNX policies need none)
    from torch import nn  # optional: inference stays importable without torch (numpy and ONNX policies need none)

    first = next((m for m in actor.modules() if isinstance(m, nn.Linear)), None)
    if first is None:
        raise ValueError(f"cannot export {type(actor).__name__}: no Linear layer to read the observation size from")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = json.dumps({"format": FORMAT, "obs_dim": first.in_features, "meta": meta or {}})
    buffer = io.BytesIO()  # serialized in memory, written by Python: a full disk is an OSError, not an abort in torch's writer
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(torch.jit.script(actor.eval()), buffer, _extra_files={EXTRA: header})
    with open(path, "wb") as f:
        f.write(buffer.getbuffer())
    return path


def load_torchscript(path: str | Path) -> TorchScriptPolicy:
    """Load a TorchScript actor file (``.pt``) written by :func:`export_torchscript`."""
    try:
        import torch  # optional: inference stays importable without torch (numpy and ONNX policies need none)
    except ImportError as exc:
        raise ValueError(f"loading {path} (torchscript) needs torch; install it or export with --format numpy") from exc
    extra = {EXTRA: ""}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            module = torch.jit.load(str(path), map_location="cpu", _extra_files=extra)
        header = json.loads(extra[EXTRA] or "{}")
    except (RuntimeError, ValueError, OSError) as exc:
        raise ValueError(f"{path} is not a coin_app TorchScript policy file (.pt): {exc}") from exc
    if header.get("format") != FORMAT:
        raise ValueError(f"{path} is not a coin_app TorchScript policy file (format {FORMAT!r} expected)")
    return TorchScriptPolicy(module.eval(), header["obs_dim"], header.get("meta"))
