"""Where the replay's camera stands: it frames every moving body over the whole replay, from a
side no static obstacle hides (docs/viewer.md)."""

from __future__ import annotations

import math

import numpy as np

FOV = math.radians(50)  # the replay camera's vertical field of view [rad]
FILL = 0.8  # the framed sphere spans this fraction of the field of view (room for the plot and the playback bar)


def corners(vertices: np.ndarray, placements: np.ndarray) -> np.ndarray:
    """(frames, 8, 3): the world corners of the box that bounds `vertices` (in their own frame),
    at each of `placements` (frames, 4, 4): the mesh lies inside them at every frame."""
    lo, hi = vertices.min(0).astype(float), vertices.max(0).astype(float)
    box = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    return box @ placements[:, :3, :3].transpose(0, 2, 1) + placements[:, None, :3, 3]


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


def camera(center, radius: float, up, obstacles=(), halfspaces=(), fov: float = FOV):
    """(position, look_at) of a camera with vertical field of view `fov` [rad] that sees the sphere
    (center, radius) within FILL of that field, whatever the window's aspect (wider than tall):
    from 25 degrees above the horizon (`up` from gravity), at the first of 12 azimuths whose line
    of sight misses every static obstacle (world AABBs (lo, hi)) and lies on the free side of
    every half-space (n, d); higher (45, then 70 degrees) where none does."""
    c, up = np.asarray(center, float), np.asarray(up, float) / np.linalg.norm(up)
    e1 = np.cross(up, [0.0, 1.0, 0.0] if abs(up[1]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    dist = max(radius, 0.05) / math.sin(FILL * fov / 2)
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
