"""CPU scheduling of a process: real-time priority for the control loop and the operator's orders.

Linux only (``os.sched_setscheduler``). A policy set on a process's main thread before it starts
others (its Zenoh session's, cflib's) is inherited by each of them, so every role sets its own
policy first thing, before its session opens.

Why the control processes may run at a real-time priority (``tether run --rt-priority``): under
the default policy a process that wakes up on a CPU held by another job waits for the scheduler's
next tick to preempt it (a few ms on this kernel), at every hop of a sample: timer, Zenoh's
threads, the router, the subscriber's threads, the event loop. Measured on a 2-vCPU machine with
two CPU-bound jobs beside Section 4 in real time, even at ``nice 19``: an agent's own measurement
was up to 1.1 s old, 30-63 % of the agents' ticks had inputs older than a period and failsafes
fired; at ``SCHED_RR`` priority 10, 99.6-100 % of the ticks had fresh inputs, the oldest
measurement was 10-20 ms old and the formation-error envelope matched the lockstep run's to 0.1 %
(``docs/runtime.md``, *Real-time priority*). A ``SCHED_RR`` process preempts every normal one at once; the kernel's
real-time throttling (``/proc/sys/kernel/sched_rt_runtime_us``, 95 % of each second by default)
still leaves the others some CPU should one spin.

Real time takes :data:`DEFAULT_PRIORITY` by default where the process is permitted to
(:func:`apply_best`), and says in one line why not where it is not. The operator gateway, the
router of the operator's ``land``/``estop`` and tools, runs one step below the control processes
(:func:`gateway_priority`): above every normal process, so that an order gets through a busy host,
and below the control loops, so that a flood of its links cannot delay them.
"""

from __future__ import annotations

import os

RR_MIN, RR_MAX = 1, 99
"""The ``SCHED_RR`` priorities Linux grants (``sched_get_priority_min/max``)."""


DEFAULT_PRIORITY = 10
"""The ``SCHED_RR`` priority a real-time run takes when none is given (``--rt-priority``)."""

HOW_TO_PERMIT = "root, CAP_SYS_NICE, or an rtprio limit of at least {p}: `ulimit -r`, /etc/security/limits.conf"


class SchedError(RuntimeError):
    """The policy cannot be applied here: ``"<why>; <how to fix it>"`` (the caller names its option)."""


def check_priority(priority: int) -> str | None:
    """Why ``priority`` cannot be a real-time priority, or None. 0 means the normal policy
    (``SCHED_OTHER``, nice 0)."""
    if not (priority == 0 or RR_MIN <= priority <= RR_MAX):
        return f"is {priority}; give {RR_MIN}..{RR_MAX} (SCHED_RR, e.g. 10), or 0 for the normal policy"
    return None


def apply(priority: int) -> str:
    """Put this process's main thread (and the threads it starts from now on) at ``SCHED_RR``
    ``priority``, or back at the normal policy for 0. Returns what was applied, for the log;
    :class:`SchedError` if the range is wrong or the system refuses (no privilege)."""
    why = check_priority(priority)
    if why is not None:
        raise SchedError(why)
    if not hasattr(os, "sched_setscheduler"):
        raise SchedError("this system has no sched_setscheduler (Linux only); run without it")
    if priority == 0:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))  # lowering is always allowed
        return "SCHED_OTHER"
    try:
        os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(priority))
    except PermissionError:
        raise SchedError(f"real-time scheduling is not permitted for this user (it needs "
                         f"{HOW_TO_PERMIT.format(p=priority)}); run without it") from None
    except OSError as exc:
        raise SchedError(f"SCHED_RR {priority} refused ({exc.strerror}); run without it") from None
    return f"SCHED_RR {priority}"


def lower_priority() -> str:
    """Put this process (and the threads it starts from now on) at the lowest CPU priority:
    ``SCHED_IDLE`` (runs only when no normal process wants the CPU; allowed unprivileged since
    Linux 2.6.39), else nice 19. Returns what was applied, for the log."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        return "SCHED_IDLE"
    except (AttributeError, OSError):
        os.nice(19 - os.nice(0))
        return f"nice {os.nice(0)}"



def apply_best(priority: int = DEFAULT_PRIORITY) -> tuple[int, str]:
    """Real time's default: ``SCHED_RR`` ``priority`` where this process is permitted it, else the
    normal policy. Never raises for want of privilege. Returns the priority applied (``priority``,
    or 0 for the normal policy) and the one line for the log, which says, when it fell back, why
    and how to permit it. :class:`SchedError` only for a priority out of range."""
    if (why := check_priority(priority)) is not None:
        raise SchedError(why)
    if priority == 0:
        return 0, apply(0)
    try:
        return priority, apply(priority)
    except SchedError:
        pass
    try:
        applied = apply(0)
    except SchedError:  # not Linux: the policy this process has is the only one
        applied = "the system's default policy"
    return 0, (f"{applied}: SCHED_RR {priority} is not permitted for this user (it needs "
               f"{HOW_TO_PERMIT.format(p=priority)}); on a busy host ticks may start late and failsafes fire (docs/runtime.md)")


def gateway_priority(control: int) -> int:
    """The operator gateway's priority when the control processes run at ``control`` (0: normal
    policy): one ``SCHED_RR`` step below them (``RR_MIN`` at least), so that it preempts every normal
    process (a busy host's work) and never the control loops; the normal policy beside normal ones."""
    if (why := check_priority(control)) is not None:
        raise SchedError(why)
    return max(RR_MIN, control - 1) if control else 0
