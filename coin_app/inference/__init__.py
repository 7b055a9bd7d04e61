"""Ray-free inference: exported actor files (numpy, TorchScript, ONNX), switching pairs, and one loader."""

from coin_app.inference.formats import FORMATS, export_policy, load_policy
from coin_app.inference.layers import ExportedPolicy
from coin_app.inference.numpy_policy import NumpyPolicy, export_numpy

__all__ = ["FORMATS", "ExportedPolicy", "NumpyPolicy", "export_numpy", "export_policy", "load_policy"]
