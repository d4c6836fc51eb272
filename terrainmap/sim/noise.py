"""Seeded value noise and its multi-octave sum (fBm), vectorised over arrays of points.

Used twice: to build terrain relief (fBm over the height grid) and to texture surfaces in
world coordinates (so a surface point looks the same from both cameras). Each octave reads the
same periodic random table through its own rotation and offset, which hides the table's axes and
period. Octaves finer than the pixel footprint can be faded out (``footprint_m``), which keeps
distant texture from aliasing into noise that differs between the left and right views.
"""

from __future__ import annotations

import numpy as np

_TABLE = 256


class ValueNoise:
    """Smooth random function of 2-D coordinates, values in about [-1, 1].

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of the random table and of the per-octave rotations (deterministic for a seed).
    octaves : int
        Number of distinct rotations/offsets prepared for :meth:`fbm`.
    """

    def __init__(self, rng: np.random.Generator, octaves: int = 8):
        self._table = rng.uniform(-1.0, 1.0, (_TABLE, _TABLE)).astype(np.float32).ravel()
        angles = rng.uniform(0.0, 2 * np.pi, octaves)
        self._rot = np.stack([np.cos(angles), np.sin(angles)], axis=1).astype(np.float32)
        self._offset = rng.uniform(0.0, _TABLE, (octaves, 2)).astype(np.float32)

    def sample(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Noise at table coordinates ``(u, v)`` (one unit = one random node), float32."""
        fu, fv = np.floor(u), np.floor(v)
        su, sv = u - fu, v - fv
        su = su * su * (3 - 2 * su)  # smoothstep: no creases at the nodes
        sv = sv * sv * (3 - 2 * sv)
        iu = fu.astype(np.int64) & (_TABLE - 1)
        iv = fv.astype(np.int64) & (_TABLE - 1)
        iu1, iv1 = (iu + 1) & (_TABLE - 1), (iv + 1) & (_TABLE - 1)
        t = self._table
        a, b = t[iu * _TABLE + iv], t[iu1 * _TABLE + iv]
        c, d = t[iu * _TABLE + iv1], t[iu1 * _TABLE + iv1]
        return a + (b - a) * su + (c - a) * sv + (a - b - c + d) * (su * sv)

    def fbm(
        self,
        x: np.ndarray,
        y: np.ndarray,
        wavelengths_m,
        amplitudes,
        *,
        footprint_m: np.ndarray | None = None,
    ) -> np.ndarray:
        """Sum of octaves ``a_k · noise((x, y) / λ_k)``, float32, same shape as ``x``.

        ``footprint_m`` (same shape, metres): an octave fades out where its wavelength is below
        about four footprints and vanishes below two (a cheap mip-map).
        """
        x = np.asarray(x, np.float32)
        y = np.asarray(y, np.float32)
        total = np.zeros(x.shape, np.float32)
        for k, (wavelength, amplitude) in enumerate(zip(wavelengths_m, amplitudes, strict=True)):
            c, s = self._rot[k % len(self._rot)]
            ou, ov = self._offset[k % len(self._offset)]
            inv = np.float32(1.0 / wavelength)
            u = (c * x - s * y) * inv + ou
            v = (s * x + c * y) * inv + ov
            if footprint_m is None:
                total += np.float32(amplitude) * self.sample(u, v)
                continue
            weight = np.clip(np.float32(wavelength / 2) / footprint_m - 1, 0, 1)
            live = weight > 0
            if live.all():
                total += np.float32(amplitude) * weight * self.sample(u, v)
            elif live.any():
                total[live] += np.float32(amplitude) * weight[live] * self.sample(u[live], v[live])
        return total
