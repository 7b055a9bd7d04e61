"""Ray-free inference: exported actor files and their loaders (numpy ``.npz`` for now)."""

from coin_app.inference.numpy_policy import NumpyPolicy, export_numpy, load_policy

__all__ = ["NumpyPolicy", "export_numpy", "load_policy"]
