"""CPPO / MFPO neighbour sets and critic inputs against brute force and hand-built vectors."""

import numpy as np
import pytest

from coin_app.algorithms.ppo_family.neighbours import concat_critic_input, mean_field_critic_input, neighbour_indices


def brute_force(pos, group, radius, k):
    out = []
    for i in range(len(pos)):
        cand = [(np.linalg.norm(pos[i] - pos[j]), j) for j in range(len(pos)) if j != i and group[j] == group[i]]
        cand = sorted((d, j) for d, j in cand if d < radius)  # ties: lower row first
        row = [j for _, j in cand][:k]
        out.append(row + [-1] * (k - len(row)))
    return np.array(out)


@pytest.mark.parametrize("seed", range(8))
def test_neighbours_match_brute_force_on_random_layouts(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 120))
    pos = rng.uniform(-60, 60, (n, 2))
    group = rng.integers(0, 6, n)  # several env steps / episodes mixed, rows shuffled
    for radius, k in ((40.0, 4), (10.0, 3), (1e9, 7)):
        np.testing.assert_array_equal(neighbour_indices(pos, group, radius, k), brute_force(pos, group, radius, k))


def test_all_neighbours_and_empty_groups():
    pos = np.array([[0.0, 0.0], [3.0, 4.0], [100.0, 0.0], [0.0, 1.0]])
    got = neighbour_indices(pos, np.array([7, 7, 7, 9]), radius=10.0)
    np.testing.assert_array_equal(got, [[1, -1], [0, -1], [-1, -1], [-1, -1]])  # row 3 is alone at its step
    wide = neighbour_indices(pos, np.array([7, 7, 7, 9]), radius=10.0, k=4)  # more slots than any group fills
    np.testing.assert_array_equal(wide, [[1, -1, -1, -1], [0, -1, -1, -1], [-1] * 4, [-1] * 4])
    assert neighbour_indices(np.zeros((0, 2)), np.zeros(0), 10.0, 4).shape == (0, 4)


def test_critic_inputs_by_hand():
    obs = np.array([[1.0, 1.0], [2.0, 0.0], [0.0, 4.0]])
    act = np.array([[0.1, 0.2], [0.3, 0.4], [-0.5, 0.6]])
    nbr = np.array([[2, 1], [0, -1], [-1, -1]])
    cc = concat_critic_input(obs, act, nbr)
    np.testing.assert_allclose(cc[0], [1, 1, 0, 4, -0.5, 0.6, 2, 0, 0.3, 0.4], rtol=1e-6)
    np.testing.assert_allclose(cc[1], [2, 0, 1, 1, 0.1, 0.2, 0, 0, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(cc[2], [0, 4, 0, 0, 0, 0, 0, 0, 0, 0])
    mf = mean_field_critic_input(obs, act, nbr)
    np.testing.assert_allclose(mf[0], [1, 1, 1, 2, -0.1, 0.5], rtol=1e-6)  # mean of rows 2 and 1
    np.testing.assert_allclose(mf[1], [2, 0, 1, 1, 0.1, 0.2], rtol=1e-6)
    np.testing.assert_allclose(mf[2], [0, 4, 0, 0, 0, 0])
