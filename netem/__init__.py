"""Message-level network emulation of the links between tether's processes. Pure.

Kernel ``tc netem`` is not available here, could not be per link, and cannot run in simulated
time; this package applies the same impairments to messages instead, on the receive side of each
directed link ``j -> i``, inside the process that subscribes to ``j``:

* :mod:`tether.netprofile` — :class:`~tether.netprofile.LinkProfile` (delay with jitter, distribution and
  correlation; Bernoulli or Gilbert-Elliott loss; duplication; reordering; corruption; a rate limit
  with a queue; scheduled outages), its validation, named presets, and a proposed mission section
  (:class:`~tether.netprofile.Network`) that picks and swaps profiles per link;
* :mod:`netem.channel` — :class:`~netem.channel.Link`, one link's state and random streams:
  ``offer(now, payload) -> list[Delivery]``; :class:`~netem.channel.DeliveryQueue` to hold copies
  until due; :func:`~netem.channel.link_rng` to seed each link.

Time is whatever the caller passes (seconds since tick 0, simulated in lockstep, monotonic in real
time): the same code serves both clocks. The model, its formulas, the presets and the determinism
contract are in ``docs/netem.md``.
"""
