"""Graph algebra of the interaction topology (Section 2.1, Eq. 7, Lemma 3). Pure numpy, no I/O.

Indexing: agents are rows ``0..N-1`` in mission order and the virtual leader is row ``N``.
``A[i, j] = a_ij > 0`` when agent i hears node j.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from tether.mission import Mission


@dataclass(frozen=True)
class Topology:
    """The weighted directed graph of a mission in array form.

    Built from the edges in O(N + edges); the dense :attr:`adjacency` is made only when it is
    first read (the engines' and metrics' small-N algebra), never by the checks.

    Attributes:
        src, dst, weight: the edges ``src -> dst`` as index arrays sorted by ``dst`` (then ``src``),
            the form the vectorised simulator sums over.
        kappa: ``(N,)`` in-degrees ``kappa_i = sum_j a_ij`` (Eq. 17).
        starts: ``(N,)`` offset of each agent's first in-edge in the sorted edge arrays.
        slot_src, slot_weight: ``(D, N)`` the same edges laid out by slot: agent i's k-th
            in-neighbour is ``slot_src[k, i]`` with weight ``slot_weight[k, i]`` (D = the largest
            in-degree; unused slots point at the leader with weight 0).
    """

    src: np.ndarray
    dst: np.ndarray
    weight: np.ndarray
    kappa: np.ndarray
    starts: np.ndarray
    slot_src: np.ndarray
    slot_weight: np.ndarray

    @property
    def n(self) -> int:
        return len(self.kappa)

    @cached_property
    def adjacency(self) -> np.ndarray:
        """``(N+1, N+1)`` matrix ``A``; the leader's row is zero (it hears nobody). O(N^2) memory:
        built on first use, for the dense algebra of small missions."""
        a = np.zeros((self.n + 1, self.n + 1))
        a[self.dst, self.src] = self.weight
        return a


def rows(m: Mission) -> dict[int, int]:
    """Node id -> row (:meth:`Mission.index_of` for every node at once: agents in file order, the leader last)."""
    out = {a.id: k for k, a in enumerate(m.agents)}
    out[m.leader.id] = m.n
    return out


def topology(m: Mission) -> Topology:
    """Build the :class:`Topology` of a validated mission, in O(N + edges)."""
    n = m.n
    row = rows(m)
    dst = np.fromiter((row[e.dst] for e in m.edges), dtype=np.intp, count=len(m.edges))
    src = np.fromiter((row[e.src] for e in m.edges), dtype=np.intp, count=len(m.edges))
    weight = np.fromiter((e.weight for e in m.edges), dtype=float, count=len(m.edges))
    order = np.lexsort((src, dst))  # sorted by dst, then src (a valid mission has no repeated pair)
    dst, src, weight = dst[order], src[order], weight[order]
    kappa = np.bincount(dst, weights=weight, minlength=n + 1)[:n]
    if np.any(kappa <= 0):
        raise ValueError("every agent needs at least one in-neighbour (Assumption 1)")
    starts = np.searchsorted(dst, np.arange(n))
    degree = np.bincount(dst, minlength=n)
    slot = np.arange(len(dst)) - starts[dst]
    slot_src = np.full((degree.max(), n), n, dtype=np.intp)
    slot_weight = np.zeros((degree.max(), n))
    slot_src[slot, dst] = src
    slot_weight[slot, dst] = weight
    return Topology(src, dst, weight, kappa, starts.astype(np.intp), slot_src, slot_weight[:, :, None])


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


DENSE_MAX = 2000
"""Largest N whose Lemma 3 matrix :func:`lemma3_holds` computes densely (an N x N solve: 32 MB and
about a second at 2000); beyond it the lemma is taken from Assumption 1 (see there)."""


def lemma3_holds(topo: Topology, atol: float = 1e-9) -> bool:
    """Check Lemma 3 on a mission's graph; returns whether it was checked numerically.

    Up to :data:`DENSE_MAX` agents ``-L1^{-1} L2`` is computed (:func:`check_lemma3`, raises
    ``AssertionError``). Beyond, nothing is computed: under Assumption 1 (checked in O(N + edges)
    by :func:`tether.checks.unreachable_agents`) ``L1`` is a non-singular M-matrix, so
    ``-L1^{-1} L2 >= 0``, and ``L1 1 = -L2`` (the rows of L sum to 0) gives unit row sums: the
    lemma's own proof, which a dense solve would only re-confirm at O(N^2) memory and O(N^3) time.
    """
    if topo.n > DENSE_MAX:
        return False
    check_lemma3(topo.adjacency, atol)
    return True


def check_lemma3(adjacency: np.ndarray, atol: float = 1e-9) -> None:
    """Raise ``AssertionError`` unless ``-L1^{-1} L2 >= 0`` with row sums 1 (to ``atol``)."""
    m = lemma3_matrix(adjacency)
    if np.any(m < -atol):
        raise AssertionError(f"-L1^-1 L2 has negative entries: min {m.min()}")
    sums = m.sum(axis=1)
    if not np.allclose(sums, 1.0, rtol=0.0, atol=atol):
        raise AssertionError(f"-L1^-1 L2 row sums are not 1: {sums}")
