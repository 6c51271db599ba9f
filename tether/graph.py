"""Graph algebra of the interaction topology (Section 2.1, Eq. 7, Lemma 3). Pure numpy, no I/O.

Indexing: agents are rows ``0..N-1`` in mission order and the virtual leader is row ``N``.
``A[i, j] = a_ij > 0`` when agent i hears node j.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tether.mission import Mission


@dataclass(frozen=True)
class Topology:
    """The weighted directed graph of a mission in array form.

    Attributes:
        adjacency: ``(N+1, N+1)`` matrix ``A``; the leader's row is zero (it hears nobody).
        src, dst, weight: the edges ``src -> dst`` as index arrays sorted by ``dst`` (then ``src``),
            the form the vectorised simulator sums over.
        kappa: ``(N,)`` in-degrees ``kappa_i = sum_j a_ij`` (Eq. 17).
        starts: ``(N,)`` offset of each agent's first in-edge in the sorted edge arrays.
        slot_src, slot_weight: ``(D, N)`` the same edges laid out by slot: agent i's k-th
            in-neighbour is ``slot_src[k, i]`` with weight ``slot_weight[k, i]`` (D = the largest
            in-degree; unused slots point at the leader with weight 0).
    """

    adjacency: np.ndarray
    src: np.ndarray
    dst: np.ndarray
    weight: np.ndarray
    kappa: np.ndarray
    starts: np.ndarray
    slot_src: np.ndarray
    slot_weight: np.ndarray

    @property
    def n(self) -> int:
        return self.adjacency.shape[0] - 1


def in_neighbours(m: Mission, agent_id: int) -> list[tuple[int, float]]:
    """The nodes agent ``agent_id`` hears, as ``(node id, a_ij)`` pairs in row order
    (:meth:`Mission.index_of`: agents in file order, the leader last), the order
    ``agent.law.AgentLaw`` sums its neighbours in. Empty for an id that hears nobody."""
    ins = sorted((m.index_of(e.src), e.src, e.weight) for e in m.edges if e.dst == agent_id)
    return [(src, weight) for _, src, weight in ins]


def topology(m: Mission) -> Topology:
    """Build the :class:`Topology` of a validated mission."""
    n = m.n
    a = np.zeros((n + 1, n + 1))
    for e in m.edges:
        a[m.index_of(e.dst), m.index_of(e.src)] = e.weight
    dst, src = np.nonzero(a)  # row-major: sorted by dst, then src
    weight = a[dst, src]
    kappa = a[:n].sum(axis=1)
    if np.any(kappa <= 0):
        raise ValueError("every agent needs at least one in-neighbour (Assumption 1)")
    starts = np.searchsorted(dst, np.arange(n))
    degree = np.bincount(dst, minlength=n)
    slot = np.arange(len(dst)) - starts[dst]
    slot_src = np.full((degree.max(), n), n, dtype=np.intp)
    slot_weight = np.zeros((degree.max(), n))
    slot_src[slot, dst] = src
    slot_weight[slot, dst] = weight
    return Topology(a, src.astype(np.intp), dst.astype(np.intp), weight, kappa, starts.astype(np.intp),
                    slot_src, slot_weight[:, :, None])


def neighbour_sums(topo: Topology, x: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """``sum_j a_ij x_j`` for every agent i; ``x`` is ``(N+1, c)`` (leader last), result ``(N, c)``.

    Summed slot by slot (gather, multiply, add), which numpy does far faster than a segmented
    reduction when in-degrees are small; the order of the terms is each agent's sorted in-edges.
    ``weight`` may be ``topo.slot_weight`` repeated to ``(D, N, c)``: same-shape products avoid
    numpy's slow path for broadcasting over a short last axis (several times faster)."""
    w = topo.slot_weight if weight is None else weight
    acc = w[0] * np.take(x, topo.slot_src[0], axis=0)
    for k in range(1, topo.slot_src.shape[0]):
        acc += w[k] * np.take(x, topo.slot_src[k], axis=0)
    return acc


def laplacian(adjacency: np.ndarray) -> np.ndarray:
    """``L = diag(A 1) - A`` (Section 2.1)."""
    return np.diag(adjacency.sum(axis=1)) - adjacency


def partition(adjacency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 7: ``L = [[L1, L2], [0, 0]]`` with ``L1`` (N x N) among agents, ``L2`` (N x 1) agents-leader."""
    lap = laplacian(adjacency)
    n = lap.shape[0] - 1
    if np.any(lap[n] != 0):
        raise ValueError("the leader's row of the Laplacian is not zero: the leader must hear nobody")
    return lap[:n, :n], lap[:n, n:]


def lemma3_matrix(adjacency: np.ndarray) -> np.ndarray:
    """``-L1^{-1} L2`` (N x 1). Under Assumption 1 it is non-negative with unit row sums (Lemma 3)."""
    l1, l2 = partition(adjacency)
    return -np.linalg.solve(l1, l2)


def check_lemma3(adjacency: np.ndarray, atol: float = 1e-9) -> None:
    """Raise ``AssertionError`` unless ``-L1^{-1} L2 >= 0`` with row sums 1 (to ``atol``)."""
    m = lemma3_matrix(adjacency)
    if np.any(m < -atol):
        raise AssertionError(f"-L1^-1 L2 has negative entries: min {m.min()}")
    sums = m.sum(axis=1)
    if not np.allclose(sums, 1.0, rtol=0.0, atol=atol):
        raise AssertionError(f"-L1^-1 L2 row sums are not 1: {sums}")
