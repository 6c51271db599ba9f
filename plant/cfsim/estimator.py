"""The simulated Crazyflie's position estimator: the Kalman estimator's position and its variance,
modelled per axis. Pure (no sockets, no clock, no randomness).

What is modelled, after the firmware's ``kalman_core.c`` and ``crtp_localization_service.c``:

* **The estimate** ``p_hat`` [m; world] is a state of its own. Between measurements it is carried
  forward by the vehicle's true displacement (the IMU prediction, taken as exact), and its variance
  ``P`` [m^2] per axis grows by :data:`PROCESS_VAR_RATE` per second (the firmware's process noise;
  without a position source the estimate stops being trusted).
* **A position measurement** ``z`` with standard deviation ``std`` is fused by the scalar Kalman update
  ``K = P / (P + std^2)``, ``p_hat += K (z - p_hat)``, ``P = (1 - K) P`` on each axis (the firmware's
  ``kalmanCoreUpdateWithPosition`` with ``H`` a unit row), ``P`` clamped to
  [:data:`MIN_COVARIANCE`, :data:`MAX_COVARIANCE`] as ``kalman_core.c`` clamps it.
* **Where measurements come from** (:attr:`EstimatorConfig.source`): ``"onboard"`` (Lighthouse,
  Loco, a flow deck: the vehicle measures itself; modelled as a measurement of the truth every tick
  with :attr:`EstimatorConfig.onboard_std`) or ``"extpos"`` (no positioning deck: only the external
  positions a client sends, ``send_extpos`` and the packed form, each fused with the parameter
  ``locSrv.extPosStdDev``). An extpos reaches the estimate in both cases, as in the firmware.
* **A reset** (``kalman.resetEstimation``) puts ``p_hat`` at the initial position (``kalman.initialX``,
  ``Y``, ``Z``: 0) with the firmware's initial variances (100^2 on x and y, clamped to 100, and 1 on z).

Not modelled: the velocity and attitude states and their cross-covariances (the velocity estimate is
the truth, plus the optional noise of :mod:`plant.cfsim.realism`), outlier rejection, the time
stamps of measurements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

MAX_COVARIANCE = 100.0
"""Largest variance [m^2] the estimator keeps (``kalman_core.c`` MAX_COVARIANCE)."""
MIN_COVARIANCE = 1e-6
"""Smallest variance [m^2] (``kalman_core.c`` MIN_COVARIANCE)."""
INITIAL_VAR = (MAX_COVARIANCE, MAX_COVARIANCE, 1.0)
"""Variances [m^2] after a reset: ``stdDevInitialPosition_xy`` = 100 m (clamped), ``_z`` = 1 m."""
PROCESS_VAR_RATE = 1e-4
"""Growth of the position variance [m^2/s] between measurements (a modelling choice: a 10 mm
standard deviation is lost in a second without measurements)."""
EXTPOS_STD_DEFAULT = 0.01
"""``locSrv.extPosStdDev`` at boot [m] (``crtp_localization_service.c``)."""


@dataclass(frozen=True)
class EstimatorConfig:
    source: Literal["onboard", "extpos"] = "onboard"
    """Where the vehicle's position measurements come from (see the module docstring)."""
    onboard_std: float = 0.005
    """Standard deviation [m] of the onboard positioning system's measurement, one per tick."""

    def __post_init__(self) -> None:
        if self.source not in ("onboard", "extpos"):
            raise ValueError(f"source = {self.source!r}: give 'onboard' or 'extpos'")
        if not (math.isfinite(self.onboard_std) and self.onboard_std > 0.0):
            raise ValueError(f"onboard_std = {self.onboard_std!r}: give a positive number of metres")


class PositionEstimator:
    """Position estimate and variance per axis. Not thread-safe; every call returns immediately.

    Attributes:
        p: the estimate [m; world frame], shape (3,).
        var: its variance per axis [m^2], shape (3,).
        fused: external positions fused since boot; rejected: those refused (non-finite).
    """

    def __init__(self, cfg: EstimatorConfig, p0: np.ndarray) -> None:
        """``p0``: where the vehicle boots [m]. An onboard source knows it from the first tick; an
        extpos-only vehicle starts at the initial position, untrusted, as after a reset."""
        self.cfg = cfg
        self.fused = 0
        self.rejected = 0
        if cfg.source == "onboard":
            self.p = np.array(p0, dtype=float)
            self.var = np.full(3, MIN_COVARIANCE)
        else:
            self.reset()

    def reset(self) -> None:
        """``kalman.resetEstimation``: the initial position, the initial variances."""
        self.p = np.zeros(3)
        self.var = np.array(INITIAL_VAR, dtype=float)

    def predict(self, dp: np.ndarray, dt: float) -> None:
        """Carry the estimate forward by the displacement ``dp`` [m] over ``dt`` [s]; the variance grows."""
        self.p = self.p + np.asarray(dp, dtype=float)
        self.var = np.minimum(self.var + PROCESS_VAR_RATE * dt, MAX_COVARIANCE)

    def measure(self, z: np.ndarray, std: float) -> bool:
        """Fuse a position ``z`` [m] of standard deviation ``std`` [m]. A measurement with a
        non-finite value or a non-positive or non-finite ``std`` is refused (False, counted)."""
        z = np.asarray(z, dtype=float)
        if z.shape != (3,) or not np.all(np.isfinite(z)) or not (math.isfinite(std) and std > 0.0):
            self.rejected += 1
            return False
        r = std * std
        k = self.var / (self.var + r)
        self.p = self.p + k * (z - self.p)
        self.var = np.clip((1.0 - k) * self.var, MIN_COVARIANCE, MAX_COVARIANCE)
        return True

    def tick(self, dp: np.ndarray, truth_p: np.ndarray, dt: float) -> None:
        """One control period: the vehicle moved by ``dp`` [m] to ``truth_p`` [m]; predict, then, with
        an onboard source, measure the truth."""
        self.predict(dp, dt)
        if self.cfg.source == "onboard":
            self.measure(truth_p, self.cfg.onboard_std)

    def extpos(self, z: np.ndarray, std: float) -> bool:
        """An external position from the localization service (counted in :attr:`fused`)."""
        ok = self.measure(z, std)
        self.fused += ok
        return ok
