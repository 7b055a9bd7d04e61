"""The shipped policies: each loads by name without Ray or torch, says what it is, and drives as its record says."""

import subprocess
import sys

import numpy as np
import pytest

from coin_app.evaluation.arena_suite import evaluate_suite, summarize
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.inference import load_policy, shipped_policies
from coin_app.inference.shipped import REQUIRED, SHIPPED_DIR, resolve, shipped_path
from coin_app.sim.scenarios import config_from_dict
from coin_app.sim.seeds import eval_test_seeds

NAMES = list(shipped_policies())
DRIVING = [n for n in NAMES if shipped_policies()[n]["scenario"] != "arena"]
ARENA = [n for n in NAMES if shipped_policies()[n]["scenario"] == "arena"]
MAX_BYTES = 2 * 1024 * 1024  # each shipped file < 2 MB (the bound)


def test_the_catalog_names_a_driving_and_an_arena_policy_and_every_file_exists():
    assert DRIVING and ARENA
    for name in NAMES:
        record = shipped_policies()[name]
        assert all(record[k] not in (None, "") for k in REQUIRED)
        assert shipped_path(name).is_file()
    files = [p for p in SHIPPED_DIR.rglob("*") if p.is_file()]
    assert all(p.stat().st_size < MAX_BYTES for p in files), [(p.name, p.stat().st_size) for p in files]


@pytest.mark.parametrize("name", NAMES)
def test_a_shipped_policy_loads_by_name_with_ray_and_torch_blocked(name):
    # a fresh interpreter in which importing ray or torch fails: loading and one forward pass must not need them
    code = (
        "import sys\nsys.modules['ray'] = None\nsys.modules['torch'] = None\n"
        "import numpy as np\nfrom coin_app.inference import load_policy\n"
        f"p = load_policy({name!r})\n"
        "dim = getattr(p, 'obs_dim', None) or p.long.obs_dim\n"
        "a = p(np.full((3, dim), 0.5, np.float32))\nprint(dim, a.shape, bool(np.isfinite(a).all()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    dim, *rest = out.stdout.split(maxsplit=1)
    assert rest == ["(3, 2) True\n"] and int(dim) > 0


def test_an_unknown_name_is_refused_with_the_shipped_names():
    with pytest.raises(ValueError, match="does not exist .*" + NAMES[0]):
        load_policy("cig_td3-nowhere")
    assert resolve("cig_td3-nowhere") == "cig_td3-nowhere"  # not a shipped name: left as a path


@pytest.mark.parametrize("name", DRIVING)
def test_a_shipped_driving_policy_reaches_its_recorded_test_success(name):
    record = shipped_policies()[name]
    policy = load_policy(name)
    assert policy.meta["scenario"] == record["scenario"] == "intersection" and policy.meta["algo"] == record["algo"]
    config = config_from_dict(record["scenario"], policy.meta["env_config"])
    assert config.num_agents == record["num_agents"]
    test = record["test"]
    seeds = eval_test_seeds(test["episodes"])  # the fixed test seeds the record was measured on
    episodes = evaluate_policy(policy, config, seeds)
    # Deterministic actions on fixed seeds repeat on one machine, but the closed loop is chaotic: another CPU's BLAS
    # rounds the actor's products otherwise and the episodes part after some steps (0.79 on the machine that recorded
    # the figure, 0.82 on an AVX-512 one). So each figure must lie within three standard errors of the 20 episodes'
    # own spread (at least 0.03) of the record: a wrong or untrained file lies far outside.
    for key in ("success_rate", "collision_rate"):
        values = np.array([e[key] for e in episodes])
        spread = max(0.03, 3 * values.std(ddof=1) / np.sqrt(len(values)))
        assert float(values.mean()) == pytest.approx(test[key], abs=spread), key


@pytest.mark.parametrize("name", ARENA)
def test_the_shipped_arena_pair_parks_lone_vehicles_as_recorded(name):
    record = shipped_policies()[name]
    rows = evaluate_suite(name, [(1, 0)], 10, workers=1, log=lambda s: None)
    assert summarize(rows).success_to_goal_rate[0] >= record["test"]["success_to_goal_rate_1x0"] - 0.2


@pytest.mark.parametrize("name", [n for n in DRIVING if "onnx" in shipped_policies()[n]])
def test_a_shipped_onnx_twin_acts_as_its_numpy_file(name):
    # the record's ONNX file is the same actor: on observations spread over [0, 1] both act alike to float32 round-off
    pytest.importorskip("onnxruntime")
    numpy_policy = load_policy(name)
    onnx_policy = load_policy(SHIPPED_DIR / shipped_policies()[name]["onnx"])
    assert onnx_policy.obs_dim == numpy_policy.obs_dim == 91
    assert onnx_policy.meta["checkpoint"] == numpy_policy.meta["checkpoint"]
    obs = np.random.default_rng(0).uniform(0.0, 1.0, (256, 91)).astype(np.float32)
    a, b = numpy_policy(obs), onnx_policy(obs)
    assert np.abs(a).max() > 0.1  # the actor acts (a zeroed file would pass the parity below)
    np.testing.assert_allclose(a, b, atol=1e-5)
