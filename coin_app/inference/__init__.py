"""Ray-free inference: exported actor files (numpy, TorchScript, ONNX), switching pairs, shipped policies, and one loader."""

from coin_app.inference.formats import FORMATS, export_policy, load_policy
from coin_app.inference.layers import ExportedPolicy
from coin_app.inference.numpy_policy import NumpyPolicy, export_numpy
from coin_app.inference.shipped import shipped_policies

__all__ = ["FORMATS", "ExportedPolicy", "NumpyPolicy", "export_numpy", "export_policy", "load_policy", "shipped_policies"]
