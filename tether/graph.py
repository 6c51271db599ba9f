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
    """

    adjacency: np.ndarray
    src: np.ndarray
    dst: np.ndarray
    weight: np.ndarray
    kappa: np.ndarray
    starts: np.ndarray

    @property
    def n(self) -> int:
        return self.adjacency.shape[0] - 1


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
    return Topology(a, src.astype(np.intp), dst.astype(np.intp), weight, kappa, starts.astype(np.intp))


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
