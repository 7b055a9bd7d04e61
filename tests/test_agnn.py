"""The A-GNN baseline: exact loading of the released weights, the U-attention layer, the arena adapter and physics, the suite."""

import math

import numpy as np
import pytest
import torch

from coin_app.cli import main
from coin_app.evaluation.arena_suite import evaluate_suite, policy_config, run_scenario, suite_config
from coin_app.inference.agnn import WEIGHTS, AgnnArenaPolicy, UAttentionConv, graph_edges, load_agnn, node_features
from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.generator import Layout
from coin_app.sim.arena.simulator import ArenaSimulator

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def model():
    return load_agnn()


def agnn_sim(starts, targets, obstacles=()):
    """An arena simulator in the A-GNN's physics, reset on the given poses."""
    sim = ArenaSimulator(make_arena_config(dt=0.2, update_order="position_first"))
    sim.reset(Layout(np.array(starts, float), np.array(targets, float), np.array(obstacles, float).reshape(-1, 3)))
    return sim


# ---------------------------------------------------------------- loading


def test_the_released_weights_load_exactly_and_every_tensor_is_used(model):
    file = torch.load(WEIGHTS, map_location="cpu", weights_only=True)
    assert sum(p.numel() for p in model.parameters() if p.requires_grad) == 473_846  # the paper's "474k"
    state = model.state_dict()
    assert set(state) == set(file) and len(file) == 230
    assert all(torch.equal(state[k], file[k]) for k in file)
    assert not any(m.training for m in model.modules())  # eval: BatchNorm uses its running statistics
    # every parameter reaches the output: 2 vehicles and an obstacle, so both edge kinds exist
    x = node_features(
        np.array([[0.0, 0.0], [5.0, 1.0]]), np.array([0.3, -1.0]), np.array([1.0, 0.5]), np.array([[10.0, 0, 0], [-3, 4, 1]]), [[3, 2, 1.5]]
    )
    src, dst = graph_edges(2, 1)
    model.zero_grad()
    model(x, src, dst)[:2].sum().backward()
    unused = [name for name, p in model.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert unused == []
    # and so does every BatchNorm's running mean
    with torch.no_grad():
        ref = model(x, src, dst)
        stale = []
        for name, buf in model.named_buffers():
            if name.endswith("running_mean"):
                buf += 1.0
                if torch.equal(model(x, src, dst), ref):  # exact: the outputs sit near tanh's 1, where a change is ~1e-6
                    stale.append(name)
                buf -= 1.0
    assert stale == []


def test_mismatched_files_are_refused_with_one_line_naming_the_file_and_key(tmp_path):
    good = torch.load(WEIGHTS, map_location="cpu", weights_only=True)
    cases = {}
    missing = dict(good)
    del missing["block2.conv1.lin_skip.weight"]
    cases["missing.pth"] = (missing, "missing key 'block2.conv1.lin_skip.weight'")
    reshaped = dict(good)
    reshaped["block0.linear.weight"] = torch.zeros(80, 9)
    cases["reshaped.pth"] = (reshaped, r"key 'block0.linear.weight' has shape \(80, 9\), expected \(80, 8\)")
    extra = dict(good)
    extra["block4.linear.weight"] = torch.zeros(2, 2)
    cases["extra.pth"] = (extra, "unexpected key 'block4.linear.weight'")
    cases["list.pth"] = ([1, 2], "not an A-GNN state dict")
    for name, (obj, message) in cases.items():
        torch.save(obj, tmp_path / name)
        with pytest.raises(ValueError, match=message) as err:
            load_agnn(tmp_path / name)
        assert name in str(err.value) and "\n" not in str(err.value)
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match="junk.pth: not a readable A-GNN state dict"):
        load_agnn(tmp_path / "junk.pth")


# ---------------------------------------------------------------- the U-attention layer


def _bn(layer, z):
    return (z - layer.running_mean) / torch.sqrt(layer.running_var + layer.eps) * layer.weight + layer.bias


def _lin_bn(block, z, relu=True):
    h = _bn(block.bn, z @ block.linear.weight.T + block.linear.bias)
    return torch.relu(h) if relu else h


def reference_u_attention(conv, x, edges, d):
    """The supplementary's Eqs. 9-13 edge by edge: out_i = W_skip x_i + sum_j softmax_j(q_ij . k_ij / sqrt(d)) v_ij."""
    u = conv.unet
    out = x @ conv.lin_skip.weight.T + conv.lin_skip.bias
    rows = []
    for i in range(len(x)):
        incoming = [j for j, k in edges if k == i]
        if not incoming:
            rows.append(out[i])
            continue
        logits, values = [], []
        for j in incoming:
            e = torch.cat([x[i], x[j] - x[i]])[None]
            h1 = _lin_bn(u.encoder_layer1, e)
            z = _lin_bn(u.encoder_layer2, h1)
            key = _lin_bn(u.decoder1_layer1, torch.cat([_lin_bn(u.decoder1_layer2, z), h1], -1), relu=False)
            value = _lin_bn(u.decoder2_layer1, torch.cat([_lin_bn(u.decoder2_layer2, z), h1], -1), relu=False)
            logits.append(torch.einsum("d,d->", _bn(conv.query_bn, e)[0], key[0]) / math.sqrt(d))
            values.append(value[0])
        alpha = torch.softmax(torch.stack(logits), 0)
        rows.append(out[i] + torch.einsum("e,ed->d", alpha, torch.stack(values)))
    return torch.stack(rows)


def test_u_attention_matches_the_edge_by_edge_formula():
    torch.manual_seed(0)
    conv = UAttentionConv(5, 6).double().eval()
    with torch.no_grad():
        for m in conv.modules():
            if isinstance(m, torch.nn.BatchNorm1d):  # non-trivial running statistics and affine terms
                m.running_mean.normal_()
                m.running_var.uniform_(0.5, 2.0)
                m.weight.normal_()
                m.bias.normal_()
    x = torch.randn(6, 5, dtype=torch.float64)
    edges = [(1, 0), (2, 0), (3, 0), (0, 1), (4, 1), (0, 2), (5, 3), (5, 4)]  # node 5 receives nothing
    src, dst = torch.tensor([e[0] for e in edges]), torch.tensor([e[1] for e in edges])
    with torch.no_grad():
        got = conv(x, src, dst)
        want = reference_u_attention(conv, x, edges, d=6)  # the scale: sqrt of the key's latent width = out channels
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)


def test_graph_edges_and_node_features():
    src, dst = graph_edges(3, 2)
    want = {(j, i) for i in range(3) for j in range(3) if i != j} | {(o, i) for o in (3, 4) for i in range(3)}
    assert sorted(zip(src.tolist(), dst.tolist())) == sorted(want)
    assert graph_edges(1, 0)[0].numel() == 0
    x = node_features(np.array([[1.0, 2.0]]), np.array([0.5]), np.array([3.0]), np.array([[4.0, 5.0, -1.0]]), np.array([[7.0, 8.0, 2.5]]))
    np.testing.assert_allclose(x.numpy(), [[1, 2, 0.5, 3, 4, 5, -1, 0], [7, 8, 0, 0, 7, 8, 0, 2.5]])
    with pytest.raises(ValueError, match="bad A-GNN state shapes"):
        node_features(np.zeros((2, 2)), np.zeros(2), np.zeros(2), np.zeros((2, 2)), np.zeros((0, 3)))


# ---------------------------------------------------------------- the adapter and the physics


def test_position_first_step_by_hand():
    sim = agnn_sim([[1.0, 2.0, 0.3]], [[20.0, 0.0, 0.0]])
    sim.speed = np.array([2.0])
    sim.step(np.array([[0.3 / 0.8, 1.0]]))  # steering 0.3 rad, pedal 1 m/s²
    np.testing.assert_allclose(sim.pos[0], [1.0 + 2.0 * math.cos(0.3) * 0.2, 2.0 + 2.0 * math.sin(0.3) * 0.2])
    assert sim.heading[0] == pytest.approx(0.3 + 2.0 * 0.2 * math.tan(0.3) / 2.0)
    assert sim.speed[0] == pytest.approx(0.99 * 2.0 + 1.0 * 0.2)
    # the heading is wrapped to [-pi, pi)
    sim = agnn_sim([[0.0, 0.0, 3.1]], [[20.0, 0.0, 0.0]])
    sim.speed = np.array([2.0])
    sim.step(np.array([[1.0, 0.0]]))
    assert sim.heading[0] == pytest.approx(3.1 + 2.0 * 0.2 * math.tan(0.8) / 2.0 - 2 * math.pi)
    assert make_arena_config().update_order == "semi_implicit"  # the arena's default is unchanged
    with pytest.raises(ValueError, match="update_order='old'; allowed: semi_implicit, position_first"):
        make_arena_config(update_order="old")


def test_actions_are_converted_to_the_arena_convention():
    class Fixed(torch.nn.Module):
        def forward(self, x, src, dst):
            return torch.tensor([[0.5, -0.4]]).repeat(len(x), 1)  # pedal 0.5 m/s², steering -0.4 rad

    sim = agnn_sim([[0.0, 0.0, 0.0], [9.0, 9.0, 1.0]], [[5.0, 0.0, 0.0], [0.0, 9.0, 0.0]])
    actions = AgnnArenaPolicy(Fixed()).from_sim(sim)
    np.testing.assert_allclose(actions, [[-0.5, 0.5], [-0.5, 0.5]])  # (steering / 0.8 rad, pedal / 1 m/s²)
    with pytest.raises(TypeError, match="acts on the world state"):
        AgnnArenaPolicy(Fixed())(np.zeros((1, 13)))


def test_a_single_vehicle_drives_toward_a_target_ahead(model):
    policy = AgnnArenaPolicy(model)
    sim = agnn_sim([[0.0, 0.0, 0.0]], [[10.0, 0.0, 0.0]])
    first = policy.from_sim(sim)
    assert first[0, 1] > 0.5  # at rest with the target ahead: forward pedal
    for _ in range(25):  # 5 s
        sim.step(policy.from_sim(sim))
    assert sim.target_distance()[0] < 5.0  # at least half of the 10 m covered
    assert abs(sim.pos[0, 1]) < 2.0  # and roughly along the line


# ---------------------------------------------------------------- the suite


def test_suite_runs_the_agnn_in_its_physics_under_both_protocols():
    policy = AgnnArenaPolicy(load_agnn())
    cfg = policy_config(policy, 400, "agnn")
    assert (cfg.dt, cfg.update_order, cfg.max_steps, cfg.success_speed) == (0.2, "position_first", 200, 0.0)  # 40 s, nobody parks
    assert policy_config(policy, 400, "arena").success_speed == 0.05
    assert suite_config(400).dt == 0.1 and suite_config(400).max_steps == 400
    with pytest.raises(ValueError, match="bad protocol 'x'; allowed: arena, agnn"):
        suite_config(400, protocol="x")
    rows = evaluate_suite("agnn", [(1, 0)], 1, workers=1, log=lambda s: None, protocol="agnn")
    assert rows[0]["protocol"] == "agnn" and rows[0]["steps"] <= 200


def test_agnn_protocol_stops_when_all_are_still_and_scores_the_final_state():
    still = lambda obs: np.zeros((len(obs), 2))  # noqa: E731
    layout = Layout(np.array([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0]]), np.array([[1.0, 0.0, 0.1], [0.0, 20.0, 0.0]]), np.zeros((0, 3)))
    env = ArenaEnv(suite_config(400, protocol="agnn"))
    res = run_scenario(still, env, layout, protocol="agnn")
    assert res["steps"] == 10  # 10 steps (11 states) of no motion: the A-GNN simulator's early stop
    assert res["success_to_goal_rate"] == 0.5  # vehicle 0 is within 1.25 m and 0.2 rad; no speed test
    # the arena protocol parks vehicle 0 at once (speed 0 < 0.05 m/s) and runs vehicle 1 to the limit
    res = run_scenario(still, ArenaEnv(suite_config(30)), layout)
    assert res["success_to_goal_rate"] == 0.5 and res["steps"] == 30


def test_evaluate_arena_runs_the_agnn(tmp_path, capsys):
    args = ["evaluate-arena", "agnn", "--cases", "1x0", "--scenarios-per-case", "1", "--workers", "1", "--out", str(tmp_path)]
    assert main([*args, "--protocol", "agnn"]) == 0
    assert "| 1 | 0 | 1 |" in capsys.readouterr().out and "agnn protocol" in (tmp_path / "arena_table.md").read_text()
    assert main([*args, "--protocol", "seed"]) == 2
    assert "invalid choice: 'seed'" in capsys.readouterr().err
