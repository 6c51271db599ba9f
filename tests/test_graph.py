"""Graph algebra: Laplacian partition (Eq. 7) and Lemma 3 on random valid graphs."""

import numpy as np
import pytest

from tether import graph
from tether.mission import in_neighbours
from tests.factories import random_mission


@pytest.mark.parametrize("seed", range(25))
def test_lemma3_on_random_valid_graphs(seed: int) -> None:
    rng = np.random.default_rng(seed)
    m = random_mission(rng, int(rng.integers(1, 12)))
    a = graph.topology(m).adjacency
    g = graph.lemma3_matrix(a)
    assert np.all(g >= -1e-12)
    np.testing.assert_allclose(g.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    graph.check_lemma3(a)


def test_laplacian_rows_sum_to_zero_and_leader_row_is_zero() -> None:
    m = random_mission(np.random.default_rng(3), 6)
    a = graph.topology(m).adjacency
    lap = graph.laplacian(a)
    np.testing.assert_allclose(lap.sum(axis=1), 0.0, atol=1e-12)
    l1, l2 = graph.partition(a)
    assert l1.shape == (6, 6) and l2.shape == (6, 1)
    np.testing.assert_array_equal(lap[-1], 0.0)


def test_lemma3_fails_without_a_path_from_the_leader() -> None:
    # agent 2 hears only agent 1 and agent 1 only agent 2: L1 is singular, Assumption 1 fails
    a = np.zeros((3, 3))
    a[0, 1] = a[1, 0] = 1.0
    with pytest.raises(np.linalg.LinAlgError):
        graph.lemma3_matrix(a)


def test_topology_edges_sorted_and_kappa() -> None:
    m = random_mission(np.random.default_rng(7), 9)
    topo = graph.topology(m)
    assert np.all(np.diff(topo.dst) >= 0)
    np.testing.assert_allclose(np.bincount(topo.dst, topo.weight, minlength=m.n), topo.kappa)
    for e in m.edges:
        assert topo.adjacency[m.index_of(e.dst), m.index_of(e.src)] == e.weight


@pytest.mark.parametrize("seed", range(5))
def test_in_neighbours_are_the_topology_rows_in_row_order(seed: int) -> None:
    m = random_mission(np.random.default_rng(seed), 8)
    topo = graph.topology(m)
    ids = [*m.agent_ids, m.leader.id]
    for i, aid in enumerate(m.agent_ids):
        ins = in_neighbours(m, aid)
        assert [m.index_of(j) for j, _ in ins] == list(topo.src[topo.dst == i])  # ascending rows
        assert [w for _, w in ins] == list(topo.weight[topo.dst == i])
        assert {j for j, _ in ins} <= set(ids)
    assert in_neighbours(m, m.leader.id) == []


def test_topology_is_sparse_and_lemma3_dense_only_for_small_n() -> None:
    """The edge arrays are built without the (N+1)^2 matrix; Lemma 3 is solved up to DENSE_MAX agents."""
    small = random_mission(np.random.default_rng(11), 7)
    topo = graph.topology(small)
    assert "adjacency" not in vars(topo)  # not built yet
    assert graph.lemma3_holds(topo) is True
    assert topo.adjacency.shape == (8, 8)
    big = random_mission(np.random.default_rng(12), graph.DENSE_MAX + 1, duration=1.0)
    topo = graph.topology(big)
    assert graph.lemma3_holds(topo) is False
    assert "adjacency" not in vars(topo)
    np.testing.assert_allclose(np.bincount(topo.dst, topo.weight, minlength=big.n), topo.kappa)
