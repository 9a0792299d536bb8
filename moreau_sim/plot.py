"""Figures from a Trajectory (or its NPZ file): energy, gaps and percussions against time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .trajectory import Trajectory, load_trajectory


def figure(traj: Trajectory | str | Path):
    """A matplotlib Figure with three panels sharing the time axis:
    energy (T, V, T + V and the contact-work ledger E0 + sum W_c), pair gaps [m], percussions [N s]."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if not isinstance(traj, Trajectory):
        traj = load_trajectory(traj)
    a, meta = traj.arrays, traj.meta
    t = a["t"]
    fig, (ax_e, ax_g, ax_p) = plt.subplots(3, 1, figsize=(9, 8), sharex=True, constrained_layout=True)
    E = a["kinetic_energy"] + a["potential_energy"]
    ax_e.plot(t, a["kinetic_energy"], lw=1, label="kinetic T")
    ax_e.plot(t, a["potential_energy"], lw=1, label="potential V")
    ax_e.plot(t, E, lw=2, color="k", label="total T + V")
    ledger = np.cumsum(a["contact_work"] + a.get("correction_energy", 0.0 * t))
    ax_e.plot(t, E[0] + ledger, lw=1, ls="--", color="tab:red", label="E0 + contact work + correction (ledger)")
    ax_e.set_ylabel("energy [J]")
    ax_e.legend(loc="best", fontsize=8)
    pairs = meta.get("model", {}).get("collision_pairs", [])
    gaps = a["gap"]
    for k in range(gaps.shape[1]):
        ax_g.plot(t, gaps[:, k], lw=1, label=pairs[k] if k < len(pairs) else f"pair {k}")
    ax_g.axhline(0.0, color="k", lw=0.5)
    ax_g.set_ylabel("gap g [m]")
    if 0 < gaps.shape[1] <= 8:
        ax_g.legend(loc="best", fontsize=7)
    if len(a["log_P"]):
        for k in np.unique(a["log_pair"]):
            sel = a["log_pair"] == k
            ax_p.vlines(a["log_t"][sel], 0, a["log_P"][sel], lw=1,
                        label=pairs[k] if k < len(pairs) else f"pair {k}")
        imp = a["log_impact"]
        ax_p.plot(a["log_t"][imp], a["log_P"][imp], "k.", ms=4, label="new impact")
        ax_p.set_yscale("symlog", linthresh=max(1e-6, float(np.median(a["log_P"]))))
        ax_p.legend(loc="best", fontsize=7)
    ax_p.set_ylabel("percussion P [N s]")
    ax_p.set_xlabel("t [s]")
    o = meta.get("options", {})
    fig.suptitle(f"{meta.get('scene', {}).get('name', '')}  e = {o.get('restitution')}  h = {o.get('dt')} s"
                 f"  ({meta.get('status', '')})")
    return fig


def save(traj: Trajectory | str | Path, png: str | Path) -> Path:
    """Draw :func:`figure` and write it to `png`."""
    import matplotlib.pyplot as plt

    fig = figure(traj)
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
