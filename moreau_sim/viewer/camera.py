"""Where the replay's camera stands: it frames the scene from a side no static obstacle hides."""

from __future__ import annotations

import math

import numpy as np


def _segment_hits_box(a, b, lo, hi) -> bool:
    d = b - a
    t0, t1 = 0.0, 1.0
    for i in range(3):
        if abs(d[i]) < 1e-12:
            if a[i] < lo[i] or a[i] > hi[i]:
                return False
            continue
        u, v = (lo[i] - a[i]) / d[i], (hi[i] - a[i]) / d[i]
        t0, t1 = max(t0, min(u, v)), min(t1, max(u, v))
        if t0 > t1:
            return False
    return True


def camera(center, radius: float, up, obstacles=(), halfspaces=(), fov: float = math.radians(50)):
    """(position, look_at) of a camera that frames a sphere (center, radius): from 25 degrees above
    the horizon (`up` from gravity), at the first of 12 azimuths whose line of sight misses every
    static obstacle (world AABBs (lo, hi)) and lies on the free side of every half-space (n, d)."""
    c, up = np.asarray(center, float), np.asarray(up, float) / np.linalg.norm(up)
    e1 = np.cross(up, [0.0, 1.0, 0.0] if abs(up[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    dist = 0.7 * max(radius, 0.05) / math.sin(fov / 2)
    best = None
    for k in range(12):
        az = math.radians(-60 + 30 * k)
        for el in (25.0, 45.0, 70.0):
            ell = math.radians(el)
            d = math.cos(ell) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(ell) * up
            p = c + dist * d
            ok = all(np.dot(n, p) > off for n, off in halfspaces) and \
                not any(_segment_hits_box(p, c, lo, hi) for lo, hi in obstacles)
            if ok:
                return p, c
            best = best if best is not None else p
    return best, c
