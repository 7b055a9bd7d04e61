"""Exported numpy policies equal the torch actor; one policy interface for callables, checkpoints and files."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from coin_app.algorithms.td3.networks import Actor
from coin_app.evaluation.policies import as_policy
from coin_app.inference import NumpyPolicy, export_numpy, load_policy


def test_numpy_export_matches_the_torch_actor(tmp_path):
    torch.manual_seed(0)
    actor = Actor(91, hidden=(32, 16))
    path = export_numpy(actor, tmp_path / "actor.npz", meta={"scenario": "intersection"})
    assert path.name == "actor.npz"
    policy = load_policy(path)
    obs = np.random.default_rng(0).uniform(0, 1, (50, 91)).astype(np.float32)
    with torch.no_grad():
        ref = actor(torch.as_tensor(obs)).numpy()
    assert np.abs(policy(obs) - ref).max() < 1e-5
    assert policy.meta == {"scenario": "intersection"} and policy.obs_dim == 91
    assert as_policy(path)(obs).shape == (50, 2)


def test_numpy_forward_by_hand():
    # one hidden ReLU unit, tanh output: a = tanh(2 * relu(x0 - x1) - 0.5)
    p = NumpyPolicy([np.array([[1.0, -1.0]]), np.array([[2.0]])], [np.zeros(1), np.array([-0.5])], ["relu", "tanh"])
    out = p(np.array([[3.0, 1.0], [0.0, 2.0]]))
    np.testing.assert_allclose(out[:, 0], [np.tanh(3.5), np.tanh(-0.5)], rtol=1e-6)


def test_loading_needs_neither_torch_nor_ray(tmp_path):
    path = export_numpy(Actor(10, hidden=(8,)), tmp_path / "a.npz")
    code = (
        "import sys; sys.modules['torch'] = None; sys.modules['ray'] = None\n"
        "import numpy as np\nfrom coin_app.inference import load_policy\n"
        f"print(load_policy({str(path)!r})(np.zeros((3, 10))).shape)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "(3, 2)"


def test_bad_policy_sources_are_refused(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        as_policy(tmp_path / "nothing.npz")
    bogus = tmp_path / "bogus.npz"
    bogus.write_text("not numpy")
    with pytest.raises(ValueError, match="not a coin_app numpy policy"):
        as_policy(bogus)
    with pytest.raises(ValueError, match="not a complete coin_app checkpoint"):
        as_policy(tmp_path)
    with pytest.raises(TypeError, match="callable, a checkpoint directory"):
        as_policy(42)
    with pytest.raises(ValueError, match=r"shape \(N, 10\)"):
        load_policy(export_numpy(Actor(10, hidden=(8,)), tmp_path / "b.npz"))(np.zeros((2, 9)))
    with pytest.raises(ValueError, match="cannot export layer"):
        export_numpy(torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Sigmoid()), tmp_path / "c.npz")
