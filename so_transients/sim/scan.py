"""Constant-elevation scan (CES) of the LAT boresight: azimuth sweeps with finite-acceleration turnarounds.

The boresight sweeps in azimuth at constant angular speed on the sky (``sky_speed`` = az speed x
cos(el)), then turns around under constant azimuthal acceleration. One *sweep* is one
constant-velocity segment plus the turnaround that ends it, so a sweep lasts
``sweep_time = cv_time + 2 v_az / accel``; the azimuth throw follows from it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from so_transients.common.angles import DEG
from so_transients.common.step_config import setting



@dataclass(frozen=True)
class ScanPattern:
    """Parameters of a CES. Angles in degrees, speeds in deg/s, times in seconds."""

    el: float = setting(50.0, "deg", "elevation of the scan")
    az_center: float = setting(180.0, "deg", "azimuth at the middle of the throw")
    sky_speed: float = setting(1.0, "deg/s", "scan speed on the sky (azimuth speed x cos(el))")
    accel: float = setting(1.0, "deg/s^2", "azimuthal acceleration in the turnarounds")
    sweep_time: float = setting(90.0, "s", "one constant-velocity segment plus one turnaround")

    def __post_init__(self):
        if not 0 < self.el < 90:
            raise ValueError(f"elevation must be in (0, 90) deg, got {self.el}")
        if self.sky_speed <= 0 or self.accel <= 0:
            raise ValueError("sky_speed and accel must be positive")
        if self.cv_time <= 0:
            raise ValueError(f"sweep_time {self.sweep_time} s is shorter than one turnaround "
                             f"({self.turnaround_time:.1f} s)")

    @property
    def az_speed(self) -> float:
        """Azimuth speed (deg/s) giving ``sky_speed`` on the sky at this elevation."""
        return self.sky_speed / np.cos(self.el * DEG)

    @property
    def turnaround_time(self) -> float:
        return 2.0 * self.az_speed / self.accel

    @property
    def cv_time(self) -> float:
        """Duration of the constant-velocity part of a sweep."""
        return self.sweep_time - self.turnaround_time

    @property
    def az_throw(self) -> float:
        """Full azimuth range covered, turnarounds included (deg)."""
        return self.az_speed * self.cv_time + self.az_speed**2 / self.accel


def boresight(t_rel, pattern: ScanPattern):
    """Boresight az, el (radians) and sweep index at times ``t_rel`` (seconds from scan start).

    The scan starts at the low-azimuth end of a constant-velocity segment, moving towards
    increasing azimuth. Sweep ``k`` covers ``[k, k + 1) * sweep_time``: even sweeps move up in
    azimuth, odd sweeps down.
    """
    t_rel = np.asarray(t_rel, dtype=np.float64)
    v, a, tc = pattern.az_speed, pattern.accel, pattern.cv_time
    sweep = np.floor(t_rel / pattern.sweep_time).astype(np.int64)
    tau = t_rel - sweep * pattern.sweep_time
    direction = np.where(sweep % 2 == 0, 1.0, -1.0)
    half_cv = 0.5 * v * tc
    in_cv = tau < tc
    u = tau - tc
    offset = np.where(in_cv, -half_cv + v * tau, half_cv + v * u - 0.5 * a * u**2)
    az = pattern.az_center + direction * offset
    el = np.full_like(t_rel, pattern.el)
    return az * DEG, el * DEG, sweep


def constant_velocity_mask(t_rel, pattern: ScanPattern):
    """True where the boresight is in a constant-velocity part of a sweep."""
    t_rel = np.asarray(t_rel, dtype=np.float64)
    return np.mod(t_rel, pattern.sweep_time) < pattern.cv_time
