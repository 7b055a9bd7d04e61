"""Every export format (numpy, TorchScript, ONNX) returns the RLModule's forward_inference actions, loads without Ray,
and refuses bad input by name; ``python -m coin_app export`` on a real checkpoint."""

import importlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from ray.rllib.core.columns import Columns

from coin_app import training
from coin_app.adapters.lcf import encode
from coin_app.adapters.rllib_env import make_env
from coin_app.algorithms import registry
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.cli import main
from coin_app.inference import FORMATS, export_policy, load_policy


def _importable(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


# Only the ONNX cases need the optional extra (exporting needs onnx, loading onnxruntime; CI installs both):
# without it they are reported as skipped, and the numpy and TorchScript cases still run.
HAVE_ONNX = _importable("onnx") and _importable("onnxruntime")
needs_onnx = pytest.mark.skipif(not HAVE_ONNX, reason="ONNX cases need onnx and onnxruntime (pip install -r requirements-onnx.txt)")


def format_params(formats=tuple(FORMATS)) -> list:
    """``formats`` as pytest parameters, the ONNX one marked :data:`needs_onnx`."""
    return [pytest.param(fmt, marks=needs_onnx) if fmt == "onnx" else fmt for fmt in formats]


def build_module(name: str, seed: int = 0):
    """A freshly built (untrained) shared RLModule of algorithm ``name`` with every parameter perturbed."""
    torch.manual_seed(seed)  # the build draws initial weights from torch's global RNG: the same module in any test order
    module = training.fresh_module(name, seed=seed)
    env = make_env(registry.get(name).scenarios[0])
    torch.manual_seed(seed)
    with torch.no_grad():  # RLlib initializes the policy head near zero; move every weight so actions differ clearly
        for p in module.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return module, env


def module_actions(module, obs: np.ndarray) -> np.ndarray:
    """What the RLModule itself does on ``obs`` in deterministic inference, as the env applies it (the expectation)."""
    x = torch.as_tensor(obs)
    if hasattr(module, "lcf_params"):  # CoPO's policy reads the LCF feature; evaluation uses the learned mean
        x = torch.cat([x, torch.full((len(x), 1), float(encode(module.lcf_distribution()[0])))], dim=1)
    with torch.no_grad():
        out = module.forward_inference({Columns.OBS: x})
    if Columns.ACTIONS in out:  # TD3 family: the tanh actor
        return out[Columns.ACTIONS].numpy()
    mean = out[Columns.ACTION_DIST_INPUTS][:, :2]  # Gaussian (mean, log std): the mean, clipped as the env clips
    return mean.clamp(-1, 1).numpy()


@pytest.mark.parametrize("fmt", format_params())
@pytest.mark.parametrize("name", sorted(registry.ALGORITHMS))
def test_every_format_returns_the_modules_inference_actions(name, fmt, tmp_path):
    module, env = build_module(name)
    obs_dim = env.driving_env.observation_space.shape[0]
    obs = np.random.default_rng(1).uniform(-0.5, 1.5, (300, obs_dim)).astype(np.float32)
    want = module_actions(module, obs)
    assert want.shape == (300, 2) and want.std() > 0.05  # a non-trivial action spread, so parity means something
    actor = module.deterministic_actor()
    policy = load_policy(export_policy(actor, tmp_path / f"{name}{FORMATS[fmt][0]}", fmt, meta={"algo": name}))
    assert policy.obs_dim == obs_dim and policy.meta == {"algo": name}
    got = policy(obs)
    assert got.dtype == np.float32 and got.shape == want.shape
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0, err_msg=f"{name} {fmt}")
    np.testing.assert_allclose(policy(obs[:1]), want[:1], atol=1e-5, rtol=0)  # batch of one


@needs_onnx
def test_onnx_graph_by_hand(tmp_path):
    # a = clip(2 * leaky_relu(x0 - x1) - 0.5, -1, 1)
    net = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.LeakyReLU(0.01), torch.nn.Linear(1, 1), torch.nn.Hardtanh(-1.0, 1.0))
    with torch.no_grad():
        net[0].weight.copy_(torch.tensor([[1.0, -1.0]]))
        net[0].bias.zero_()
        net[2].weight.fill_(2.0)
        net[2].bias.fill_(-0.5)
    policy = load_policy(export_policy(net, tmp_path / "a.onnx", "onnx"))
    x = np.array([[3.0, 1.0], [0.0, 2.0], [0.5, 0.25]], np.float32)
    np.testing.assert_allclose(policy(x)[:, 0], [1.0, 2 * (-0.02) - 0.5, 0.0], atol=1e-7)


@pytest.mark.parametrize("fmt", format_params(["numpy", "onnx", "torchscript"]))
def test_loading_needs_no_ray(fmt, tmp_path):
    module, env = build_module("ippo")
    path = export_policy(module.deterministic_actor(), tmp_path / f"p{FORMATS[fmt][0]}", fmt)
    blocked = "['ray']" if fmt == "torchscript" else "['ray', 'torch']"  # TorchScript needs torch, nothing else does
    code = (
        f"import sys\nfor m in {blocked}: sys.modules[m] = None\n"
        "import numpy as np\nfrom coin_app.inference import load_policy\n"
        f"p = load_policy({str(path)!r})\nprint(p(np.zeros((3, p.obs_dim), np.float32)).shape)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "(3, 2)"


def test_bad_exports_and_files_are_refused(tmp_path):
    net = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Tanh())
    with pytest.raises(ValueError, match=r"unknown format 'tflite'; allowed: numpy, torchscript, onnx"):
        export_policy(net, tmp_path / "a.tflite", "tflite")
    with pytest.raises(ValueError, match=r"must end in \.onnx for format 'onnx'"):
        export_policy(net, tmp_path / "a.npz", "onnx")
    assert not list(tmp_path.iterdir())
    for suffix, kind in ((".pt", "TorchScript"), (".npz", "numpy")):
        bad = tmp_path / f"bad{suffix}"
        bad.write_bytes(b"not a policy")
        with pytest.raises(ValueError, match=f"not a coin_app {kind} policy file"):
            load_policy(bad)
    other = tmp_path / "plain.pt"  # a valid TorchScript file that coin_app did not write
    torch.jit.save(torch.jit.script(net), str(other))
    with pytest.raises(ValueError, match="format 'coin_app.torchscript.v1' expected"):
        load_policy(other)
    (tmp_path / "w.h5").write_bytes(b"x")
    with pytest.raises(ValueError, match=r"no known policy suffix; allowed: \.npz \(numpy\), \.pt \(torchscript\), \.onnx \(onnx\)"):
        load_policy(tmp_path / "w.h5")


@needs_onnx
def test_bad_onnx_files_are_refused(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"not a policy")
    with pytest.raises(ValueError, match="not a coin_app ONNX policy file"):
        load_policy(bad)
    net = torch.nn.Sequential(torch.nn.Linear(3, 2), torch.nn.Tanh())
    with pytest.raises(ValueError, match="shape \\(N, 3\\)"):
        load_policy(export_policy(net, tmp_path / "ok.onnx", "onnx"))(np.zeros((2, 4)))


@pytest.fixture(scope="module")
def ippo_checkpoint(ray_session, tmp_path_factory):
    """An untrained IPPO checkpoint (its policy head perturbed) written the way ``train`` writes them."""
    out = tmp_path_factory.mktemp("ckpt") / "checkpoint"
    cfg = training.build_config("ippo", "intersection", {"num_agents": 4, "hidden": 16}, 0)
    algo = cfg.build_algo()
    module = algo.learner_group._learner.module[SHARED_MODULE_ID]
    with torch.no_grad():
        for p in module.parameters():
            p.add_(0.3 * torch.randn_like(p))
    training.save(algo, out, {"algo": "ippo", "scenario": "intersection", "seed": 0, "env_config": {"num_agents": 4}})
    algo.stop()
    return out


@pytest.mark.parametrize("fmt", format_params())
def test_cli_export_each_format(ippo_checkpoint, fmt, tmp_path, capsys):
    out = tmp_path / f"actor{FORMATS[fmt][0]}"
    assert main(["export", str(ippo_checkpoint), "--format", fmt, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    gap = float(text.split("forward_inference| on 256 random obs = ")[1].split()[0])
    assert gap <= 1e-5 and f"({fmt}," in text
    policy = load_policy(out)
    assert policy.meta["algo"] == "ippo" and policy.meta["env_config"] == {"num_agents": 4}
    # the evaluator takes the exported file like any policy: identical returns to the checkpoint itself
    assert main(["evaluate", str(out), "--seeds", "5"]) == 0
    from_file = capsys.readouterr().out
    assert main(["evaluate", str(ippo_checkpoint), "--seeds", "5"]) == 0
    assert capsys.readouterr().out.split("success rate")[1] == from_file.split("success rate")[1]


def test_cli_export_refuses_bad_input(ippo_checkpoint, tmp_path, capsys):
    assert main(["export", str(ippo_checkpoint), "--format", "tflite", "--out", str(tmp_path / "a.tflite")]) == 2
    assert "unknown format 'tflite'" in capsys.readouterr().err
    assert main(["export", str(ippo_checkpoint), "--format", "onnx", "--out", str(tmp_path / "a.pt")]) == 2
    assert "must end in .onnx" in capsys.readouterr().err
    assert main(["export", str(tmp_path / "missing"), "--format", "numpy", "--out", str(tmp_path / "a.npz")]) == 2
    assert "missing" in capsys.readouterr().err
    assert not list(tmp_path.glob("a.*"))


def test_a_failed_export_leaves_the_earlier_file_intact(tmp_path, monkeypatch):
    import coin_app.inference.numpy_policy as numpy_policy

    actor = torch.nn.Sequential(torch.nn.Linear(91, 8), torch.nn.Tanh(), torch.nn.Linear(8, 2), torch.nn.Tanh())
    path = export_policy(actor, tmp_path / "actor.npz", "numpy")
    before = path.read_bytes()

    def full_disk(*args, **kwargs):
        args[0].write(b"half a file")  # what a write cut by a full disk leaves behind
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(numpy_policy.np, "savez", full_disk)
    with pytest.raises(OSError, match="No space left"):
        export_policy(actor, path, "numpy")
    assert path.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == ["actor.npz"]


FILE_LIMIT = """
import resource, signal, sys
from pathlib import Path
import torch
from coin_app.inference import export_policy
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit then fails (EFBIG), as one on a full disk (ENOSPC)
actor = torch.nn.Sequential(torch.nn.Linear(91, 64), torch.nn.Tanh(), torch.nn.Linear(64, 2), torch.nn.Tanh())
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))  # every format's file of this actor is larger
try:
    export_policy(actor, Path(sys.argv[1]), sys.argv[2])
except OSError as exc:
    print("OSError", exc.errno)
    sys.exit(3)
"""


@pytest.mark.parametrize(("fmt", "suffix"), [("numpy", ".npz"), ("torchscript", ".pt"), ("onnx", ".onnx")])
def test_an_export_cut_short_by_the_disk_is_an_oserror_and_leaves_the_earlier_file(fmt, suffix, tmp_path):
    """A real write failure (the file-size limit) in every format: an OSError (TorchScript's own writer used to abort the
    process, exit 134), the earlier file byte for byte, nothing partial left."""
    if fmt == "onnx":
        pytest.importorskip("onnx")
    path = tmp_path / f"actor{suffix}"
    path.write_bytes(b"the earlier policy")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent)}
    done = subprocess.run([sys.executable, "-c", FILE_LIMIT, str(path), fmt], capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 3 and done.stdout.split()[0] == "OSError", (done.returncode, done.stderr[-2000:])
    assert path.read_bytes() == b"the earlier policy" and sorted(p.name for p in tmp_path.iterdir()) == [path.name]
