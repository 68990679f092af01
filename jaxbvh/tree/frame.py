"""Scene-relative coordinates: the map between world space and the frame trees live in.

float32 cannot tell 1e7 from 1e7 + 0.5, nor square 1e30; a mesh far from the origin or
at an extreme scale loses its small triangles or overflows its areas. We therefore build
in a *scene frame*: ``local = (world - origin) / scale`` with ``origin`` the centre of
the scene box and ``scale`` a power of two near its half-extent, so that local
coordinates lie in [-1, 1]. The map is computed in float64 on the host; only the local
coordinates go to the device. Division by a positive number and subtraction are
monotone, so boxes that nest in world space still nest in the frame.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Frame:
    """``local = (world - origin) / scale``; ``origin`` float64 [3], ``scale`` > 0."""

    origin: np.ndarray
    scale: float

    @staticmethod
    def identity() -> "Frame":
        return Frame(np.zeros(3), 1.0)

    @staticmethod
    def fit(lo: np.ndarray, hi: np.ndarray) -> "Frame":
        """Frame centred on the box of all ``lo`` / ``hi`` [n, 3] (world, float64)."""
        lo = np.asarray(lo, np.float64)
        hi = np.asarray(hi, np.float64)
        box_lo, box_hi = lo.min(axis=0), hi.max(axis=0)
        origin = 0.5 * box_lo + 0.5 * box_hi  # no overflow near float64 max
        half = float(np.max(0.5 * box_hi - 0.5 * box_lo))
        if half > 0:
            # round up to a power of two: scaling by it is exact
            scale = float(np.ldexp(1.0, int(np.frexp(half)[1])))
        else:
            scale = 1.0
        return Frame(origin, scale)

    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and not np.any(self.origin)

    def to_local(self, world: np.ndarray) -> np.ndarray:
        """World points / box corners [..., 3] float64 -> frame coordinates (float64)."""
        return (np.asarray(world, np.float64) - self.origin) / self.scale

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Frame coordinates [..., 3] -> world (float64)."""
        return np.asarray(local, np.float64) * self.scale + self.origin
