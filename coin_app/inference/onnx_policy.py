"""The ONNX export format: the actor MLP as an ONNX graph (``.onnx``) run by onnxruntime, without torch or Ray.

The graph is written directly from the actor's layers (:func:`~coin_app.inference.layers.mlp_layers`):
per layer one ``Gemm`` (``x W^T + b``) and its activation (``Relu``, ``Tanh``,
``LeakyRelu`` alpha 0.01, ``Clip`` to [-1, 1]); input ``obs`` (batch, obs_dim) float32, output
``action``; opset 17. Metadata properties ``coin_app_format`` = ``"coin_app.onnx_mlp.v1"`` and
``coin_app_meta`` (JSON). Exporting needs the ``onnx`` package, loading ``onnxruntime``: the
optional extra ``requirements-onnx.txt``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.inference.layers import ExportedPolicy, check_layers, mlp_layers

FORMAT = "coin_app.onnx_mlp.v1"
OPSET = 17
EXTRA_HINT = "pip install -r requirements-onnx.txt"


class OnnxPolicy(ExportedPolicy):
    """An ONNX actor ``(N, obs_dim) -> (N, act_dim)`` on onnxruntime's CPU provider (``threads`` intra-op threads)."""

    format_name = "onnx"

    def __init__(self, path: str | Path, threads: int = 1):
        try:
            import onnxruntime as ort  # optional: onnx / onnxruntime come with requirements-onnx.txt
        except ImportError as exc:
            raise ValueError(f"loading {path} (onnx) needs onnxruntime ({EXTRA_HINT})") from exc
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        options.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ValueError(f"{path} is not a coin_app ONNX policy file (.onnx): {exc}") from exc
        props = self.session.get_modelmeta().custom_metadata_map
        if props.get("coin_app_format") != FORMAT:
            raise ValueError(f"{path} is not a coin_app ONNX policy file (format {FORMAT!r} expected)")
        super().__init__(self.session.get_inputs()[0].shape[1], json.loads(props.get("coin_app_meta", "{}")))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, act_dim) for observations (N, obs_dim)."""
        return self.session.run(None, {"obs": self.batch(obs)})[0]


def export_onnx(actor: Any, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write a torch actor MLP to ``path`` as an ONNX graph; returns the path."""
    try:
        import onnx  # optional: onnx / onnxruntime come with requirements-onnx.txt
        from onnx import TensorProto, helper, numpy_helper  # optional: onnx / onnxruntime come with requirements-onnx.txt
    except ImportError as exc:
        raise ValueError(f"--format onnx needs the onnx package ({EXTRA_HINT})") from exc
    weights, biases, acts = mlp_layers(actor)
    check_layers(weights, biases, acts)
    nodes, inits, x = [], [], "obs"
    for k, (w, b, act) in enumerate(zip(weights, biases, acts)):
        inits += [numpy_helper.from_array(w.astype(np.float32), f"W{k}"), numpy_helper.from_array(b.astype(np.float32), f"b{k}")]
        y = f"h{k}"
        nodes.append(helper.make_node("Gemm", [x, f"W{k}", f"b{k}"], [y], transB=1))
        if act == "relu":
            nodes.append(helper.make_node("Relu", [y], [f"a{k}"]))
        elif act == "tanh":
            nodes.append(helper.make_node("Tanh", [y], [f"a{k}"]))
        elif act == "leaky_relu":
            nodes.append(helper.make_node("LeakyRelu", [y], [f"a{k}"], alpha=0.01))
        elif act == "clip":
            inits += [numpy_helper.from_array(np.float32(v), f"clip{k}_{n}") for n, v in (("lo", -1.0), ("hi", 1.0))]
            nodes.append(helper.make_node("Clip", [y, f"clip{k}_lo", f"clip{k}_hi"], [f"a{k}"]))
        x = f"a{k}" if act != "identity" else y
    nodes.append(helper.make_node("Identity", [x], ["action"]))
    graph = helper.make_graph(
        nodes,
        "coin_app_actor",
        [helper.make_tensor_value_info("obs", TensorProto.FLOAT, ["batch", weights[0].shape[1]])],
        [helper.make_tensor_value_info("action", TensorProto.FLOAT, ["batch", weights[-1].shape[0]])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="coin_app")
    model.ir_version = 8  # readable by every onnxruntime since 1.11
    helper.set_model_props(model, {"coin_app_format": FORMAT, "coin_app_meta": json.dumps(meta or {})})
    onnx.checker.check_model(model)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(path))
    return path


def load_onnx(path: str | Path, threads: int = 1) -> OnnxPolicy:
    """Load an ONNX actor file (``.onnx``) written by :func:`export_onnx`."""
    return OnnxPolicy(path, threads)
