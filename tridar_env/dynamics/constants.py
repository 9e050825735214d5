"""Physical constants of the truth dynamics [SI]: Earth (WGS-84 / EGM-96), standard gravity."""

from __future__ import annotations

__all__ = ["G0", "J2_EARTH", "MU_EARTH", "R_EARTH"]

MU_EARTH = 3.986004418e14
"""Earth's gravitational parameter [m^3/s^2] (WGS-84 / EGM)."""
R_EARTH = 6378137.0
"""Earth's equatorial radius [m] (WGS-84)."""
J2_EARTH = 1.08262668e-3
"""Earth's second zonal harmonic [-] (EGM-96, unnormalised)."""
G0 = 9.80665
"""Standard gravity [m/s^2], the Isp reference."""
