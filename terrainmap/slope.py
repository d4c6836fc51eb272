"""Terrain slope from the analytic derivative of the spline surface (paper step 4).

The slope angle at (x, y) is ``atan(‖∇S‖)`` (radians, 0 = level), where ∇S = (∂S/∂x, ∂S/∂y)
comes from the quotient rule on eq. 2 (:meth:`RationalSurface.gradient`), never from finite
differences: :func:`slope_at` at any points, :func:`layers` at the cell centres.
"""

from __future__ import annotations

import numpy as np

from .bspline import RationalSurface


def slope_angle(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Slope angle (rad) from the gradient components (dimensionless)."""
    return np.arctan(np.hypot(gx, gy))


def slope_at(surface: RationalSurface, x, y) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(slope_rad, dz_dx, dz_dy)`` at broadcastable points (x, y) in metres, vehicle frame;
    outside the area of interest, those at the nearest point of its edge (:class:`RationalSurface`)."""
    gx, gy = surface.gradient(x, y)
    return slope_angle(gx, gy), gx, gy


def layers(elevation: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> dict[str, np.ndarray]:
    """Grid layers from heights and gradient: float32 ``elevation`` (m), ``slope`` (rad),
    ``dz_dx``, ``dz_dy``, all shaped like the inputs."""
    return {
        "elevation": elevation.astype(np.float32),
        "slope": slope_angle(gx, gy).astype(np.float32),
        "dz_dx": gx.astype(np.float32),
        "dz_dy": gy.astype(np.float32),
    }
