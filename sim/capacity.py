"""What the reference simulator can take on here, checked before it starts: a mission's continuous
mode is refused when its RK4 substeps or its dense matrices would not fit (:func:`problems`).

The mission's own size (ticks, agents, the run file) is checked where the mission is validated
(``tether.checks``); this module adds what only the simulator's mode and engine decide.
"""

from __future__ import annotations

from sim import refsim
from sim.setup import Engine, Setup
from tether import mission as ms
from tether.checks import MAX_AGENT_TICKS
from tether.graph import DENSE_MAX


def problems(m: ms.Mission, mode: str, substeps: int, engine: Engine, live: bool) -> list[tuple[str, str]]:
    """Why ``refsim.simulate(m, mode, substeps=substeps, engine=engine)`` (with a live view when
    ``live``) should not start: ``[(option, what is wrong and the fix)]``, empty when it may.
    Computes the agents' graph blocks for a large continuous run; allocates nothing run-sized."""
    if mode != "continuous":
        return []
    work = m.steps * substeps * m.n
    if work > MAX_AGENT_TICKS:
        return [("--substeps", f"is {substeps}: {m.steps} steps x {substeps} substeps x {m.n} agents = "
                               f"{work:.3g} agent-substeps, beyond the limit of {MAX_AGENT_TICKS:.0e}; use fewer "
                               "substeps (10 is plenty for RK4) or a shorter --duration")]
    if m.n <= DENSE_MAX:
        return []
    # the numpy path inverts the dense N x N matrix L1; the compiled kernel only each strongly
    # connected block of the agents' graph (sim.kernel.solve_plan)
    from sim import kernel

    s = Setup.of(m)
    block = kernel.largest_block(m.n, s.topo.src, s.topo.dst)
    try:
        compiled = refsim.takes_kernel(s, engine, None) and not live
    except ValueError:  # engine "compiled" where it cannot run: refused here as the numpy path
        compiled = False
    if compiled and block <= DENSE_MAX:
        return []
    why = (f"inverts the dense {m.n} x {m.n} matrix L1 (about {8 * m.n * m.n / 2**30:.3g} GiB and O(N^3) "
           "time) on the numpy path (--engine numpy, --live, numba missing or a disturbance it does not know)"
           if not compiled else
           f"inverts the largest strongly connected block of the agents' graph, {block} agents here")
    return [("--mode", f"is continuous, which {why}; use --mode discrete (sparse, the runtime's semantics), or at "
                       f"most {DENSE_MAX} agents in one strongly connected block with the compiled engine")]


def slow_path() -> str | None:
    """One line for an install without the compiled kernels (numba, the ``[fast]`` extra), whose
    simulator and in-process engine then run their numpy and Python paths; None when they can run."""
    from sim import kernel

    if kernel.AVAILABLE:
        return None
    return ("note: numba is not installed, so the simulator runs its numpy and Python paths: the same results, "
            "several times slower (about 10x for a sweep); pip install 'tether[fast]' for the compiled kernels")
