"""A software Crazyflie that real cflib flies over ``udp://``: CRTP over UDP, a firmware-like
commander, supervisor and high-level commander, and :class:`plant.quadrotor.Quadrotor` as the body.

| module | what |
|---|---|
| :mod:`plant.cfsim.crtp` | the packet codec: ports, channels, command codes, header byte (pure) |
| :mod:`plant.cfsim.commander` | setpoint types, the setpoint slot and its priorities, the low-level decoders (pure) |
| :mod:`plant.cfsim.high_level` | the high-level commander: take-off, landing, go-to, spiral, trajectories (pure) |
| :mod:`plant.cfsim.trajectory` | the trajectory memory and piecewise poly4d evaluation (pure) |
| :mod:`plant.cfsim.toc` | the log and param tables of contents and their wire forms (pure) |
| :mod:`plant.cfsim.services` | the log, param and mem services (pure) |
| :mod:`plant.cfsim.supervisor` | arming, the flying state, the setpoint watchdog and the lock (pure) |
| :mod:`plant.cfsim.controller` | setpoint and state estimate to a command of the quadrotor (pure) |
| :mod:`plant.cfsim.motors` | the thrust map between PWM units and newtons (pure) |
| :mod:`plant.cfsim.world` | the quadrotor above its floor (pure) |
| :mod:`plant.cfsim.firmware` | one vehicle: routes each port to its part, runs the 100 Hz tick, logs its state (pure) |
| :mod:`plant.cfsim.server` | the asyncio UDP endpoints and the 100 Hz ticker |
| ``python -m plant.cfsim`` | start several vehicles on ports 19850 and up |

``docs/cfsim.md`` describes what is implemented and how it maps to the real firmware.
"""
