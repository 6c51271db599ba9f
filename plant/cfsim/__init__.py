"""A software Crazyflie that real cflib flies over ``udp://``: CRTP over UDP, a firmware-like
commander, supervisor and high-level commander, and :class:`plant.quadrotor.Quadrotor` as the body.

| module | what |
|---|---|
| :mod:`plant.cfsim.crtp` | the packet codec: ports, channels, header byte (pure) |
| :mod:`plant.cfsim.toc` | the log and param tables of contents and their wire forms (pure) |
| :mod:`plant.cfsim.trajectory` | the trajectory memory and piecewise poly4d evaluation (pure) |
| :mod:`plant.cfsim.firmware` | commander, watchdog, high-level commander, log blocks, params, world (pure) |
| :mod:`plant.cfsim.server` | the asyncio UDP endpoints and the 100 Hz ticker |
| ``python -m plant.cfsim`` | start several vehicles on ports 19850 and up |

``docs/cfsim.md`` describes what is implemented and how it maps to the real firmware.
"""
