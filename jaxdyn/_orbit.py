"""A circular orbit and the geomagnetic field along it, for the effects that need them
(gravity gradient, magnetic torque rods): written once, here.

The geomagnetic field is the tilted dipole of IGRF-13 at epoch 2020.0 (Alken et al. 2021,
"International Geomagnetic Reference Field: the thirteenth generation", Earth Planets Space
73:49): `g10 = -29404.8 nT`, `g11 = -1450.9 nT`, `h11 = 4652.5 nT`, reference radius
`a = 6371.2 km`. Outside the Earth the dipole's field is
`B(r) = (a / |r|)^3 (3 (m . r_hat) r_hat - m)` with `m = (g11, h11, g10)` in the Earth-fixed
frame (x at longitude 0, z north); the Earth turns under the inertial frame at
`EARTH_RATE`, by `earth_angle` (the Greenwich angle) at `t = 0`.
"""

import jax.numpy as jnp

MU_EARTH = 3.986004418e14
"""Earth's gravitational parameter (m^3/s^2, WGS-84)."""
EARTH_RADIUS = 6378137.0
"""Earth's equatorial radius (m, WGS-84): altitudes are above it."""
EARTH_RATE = 7.2921150e-5
"""Earth's rotation rate (rad/s)."""
IGRF_RADIUS = 6371200.0
"""IGRF reference radius `a` (m)."""
DIPOLE_NT = (-1450.9, 4652.5, -29404.8)
"""IGRF-13 (2020.0) dipole coefficients as the Earth-fixed vector `(g11, h11, g10)`, in nT."""


def orbit_rate(altitude):
    """Mean motion `sqrt(mu / r^3)` (rad/s) of a circular orbit at `altitude` (m)."""
    return jnp.sqrt(MU_EARTH / (EARTH_RADIUS + altitude) ** 3)


def orbit_direction(t, rate, phase, inclination=0.0, node=0.0):
    """Unit vector from the Earth's centre to the spacecraft, inertial frame, on a circular
    orbit with mean motion `rate`, argument of latitude `phase` at `t = 0`, `inclination` and
    right ascension of the ascending `node` (rad)."""
    u = rate * t + phase
    cu, su = jnp.cos(u), jnp.sin(u)
    ci, si = jnp.cos(inclination), jnp.sin(inclination)
    cn, sn = jnp.cos(node), jnp.sin(node)
    return jnp.stack([cn * cu - sn * su * ci, sn * cu + cn * su * ci, su * si])


def dipole_field(t, r_hat, radius, earth_angle=0.0):
    """The IGRF-13 tilted dipole's field (T) at `radius * r_hat` (inertial frame)."""
    g = earth_angle + EARTH_RATE * t
    mx, my, mz = (c * 1e-9 for c in DIPOLE_NT)
    cg, sg = jnp.cos(g), jnp.sin(g)
    m = jnp.stack([cg * mx - sg * my, sg * mx + cg * my, mz * jnp.ones_like(g)])
    scale = (IGRF_RADIUS / radius) ** 3
    return scale * (3 * jnp.dot(m, r_hat) * r_hat - m)
