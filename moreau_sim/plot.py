"""Figures from a Trajectory (or its NPZ file): energy, gaps, percussions, coordinates and
velocities against time, one colour per collision pair in every panel, the pairs that matter
most named in a legend outside the data, curves that coincide named together (docs/cli.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .trajectory import Trajectory, load_trajectory

PANELS = ("energy", "gap", "percussion", "q", "u")
DEFAULT_PANELS = ("energy", "gap", "percussion")
TOP = 8  # pairs (or coordinates) named in a legend; the others are drawn thin and grey
_CYCLE = tuple(f"C{i}" for i in range(TOP))  # the gap panel's colours when its columns are geometries, not pairs
SAME = 3e-3  # curves closer than this fraction of their panel's range everywhere are drawn once, named together


def figure(traj: Trajectory | str | Path, panels: tuple[str, ...] | list[str] = DEFAULT_PANELS):
    """A matplotlib Figure with the given `panels` (any of PANELS) sharing the time axis:
    energy [J] (T, V, T + V and the ledger E0 + sum(W_c + correction + smooth error)), gap [m] per collision pair,
    percussion [N s] per logged contact, q and u per coordinate."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    panels = tuple(panels)
    bad = [p for p in panels if p not in PANELS]
    if bad or not panels:
        raise ValueError(f"panels must be among {list(PANELS)}, got {list(panels)}")
    if not isinstance(traj, Trajectory):
        traj = load_trajectory(traj)
    a, meta = traj.arrays, traj.meta
    mm = meta.get("model", {})
    # {log_pair: name}: the listed pairs' (a scene without a pair list names the pairs its log holds: logged_pairs);
    # a joint limit's percussions are logged under pair = (number of pairs) + its index: name joint and side
    listed = mm.get("collision_pairs") or []
    pairs = {k: name for k, name in enumerate(listed)}
    pairs.update({int(k): name for k, name in mm.get("logged_pairs", {}).items()})
    pairs.update({int(lim["pair"]): f"limit {lim['name']}" for lim in mm.get("joint_limits", [])})
    colour = _pair_colours(a, a["gap"].shape[1] if mm.get("gap_columns") != "geometries" else 0, plt)
    fig, axes = plt.subplots(len(panels), 1, figsize=(11, 2.6 * len(panels) + 0.6), sharex=True,
                             constrained_layout=True, squeeze=False)
    for ax, panel in zip(axes[:, 0], panels):
        {"energy": _energy, "gap": _gaps, "percussion": _percussions, "q": _coordinates,
         "u": _coordinates}[panel](ax, panel, a, meta, pairs, colour)
        ax.grid(True, lw=0.3, alpha=0.5)
    axes[-1, 0].set_xlabel("t [s]")
    o = meta.get("options", {})
    fig.suptitle(f"{meta.get('scene', {}).get('name', '')}  e = {o.get('restitution')}  h = {o.get('dt')} s"
                 f"  ({meta.get('status', '')})")
    return fig


def _legend(ax, title=None):
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, title=title, title_fontsize=7,
                  frameon=False)


def _energy(ax, _, a, meta, pairs, colour):
    t = a["t"]
    E = a["kinetic_energy"] + a["potential_energy"]
    _curves(ax, t, [(a["kinetic_energy"], dict(lw=1, color="C0", label="kinetic T")),
                    (a["potential_energy"], dict(lw=1, color="C1", label="potential V")),
                    (E, dict(lw=2, color="k", label="total T + V"))])
    smooth = a.get("smooth_error")
    if smooth is not None and len(smooth) and np.isfinite(smooth).all():  # files before format 3 have none
        ledger, label = np.cumsum(a["contact_work"] + a["correction_energy"] + smooth), "Σ(W_c + corr. + smooth)"
    else:
        ledger, label = np.cumsum(a["contact_work"] + a["correction_energy"]), "Σ(W_c + corr.)"
    for key, name in (("actuator_work", "W_a"), ("obstacle_work", "W_o")):  # work done on it (§5.5), if any
        if key in a:
            ledger, label = ledger + np.cumsum(a[key]), label[:-1] + f" + {name})"
    ax.plot(t, E[0] + ledger, lw=1, ls="--", color="tab:red", label=f"ledger E0 + {label}")
    ax.set_ylabel("energy [J]")
    _legend(ax)


def _pair_colours(a, npairs: int, plt) -> dict[int, tuple]:
    """One distinct colour per pair that a panel names (the closest gaps, then the largest
    percussions), the same in every panel; pairs no panel names are drawn grey."""
    named = _top(-np.nanmin(a["gap"], axis=0)) if len(a["t"]) and npairs else []
    P, lp = a["log_P"], a["log_pair"]
    ids = np.unique(lp)
    named += [int(ids[i]) for i in _top(np.array([P[lp == k].sum() for k in ids]))]
    cmap = plt.get_cmap("tab10" if len(set(named)) <= 10 else "tab20")
    out: dict[int, tuple] = {}
    for k in named:
        if k not in out:
            out[k] = cmap(len(out) % cmap.N)
    return out


def _top(scores: np.ndarray, n: int = TOP) -> list[int]:
    """Indices of the n largest finite scores, largest first."""
    order = [int(i) for i in np.argsort(-scores, kind="stable") if np.isfinite(scores[i])]
    return order[:n]


def _gaps(ax, _, a, meta, pairs, colour):
    t, gaps = a["t"], a["gap"]
    if not gaps.shape[1]:
        ax.text(0.5, 0.5, "no collision pairs", transform=ax.transAxes, ha="center")
        return
    mm = meta.get("model", {})
    per_geometry = mm.get("gap_columns") == "geometries"  # more than model.GAP_PAIRS pairs: a column per geometry
    if per_geometry:
        pairs = dict(enumerate(mm.get("geometries", [])))
        colour = {k: c for k, c in zip(_top(-np.nanmin(gaps, axis=0)) if len(t) else [], _CYCLE)}
    # the pairs that come closest are the ones to see; the rest are context
    shown = set(_top(-np.nanmin(gaps, axis=0))) if len(t) else set()
    for k in range(gaps.shape[1]):
        if k not in shown:
            ax.plot(t, gaps[:, k], lw=0.5, color="0.75")
    _curves(ax, t, [(gaps[:, k], dict(lw=1.2, color=colour.get(k, "0.4"), label=pairs.get(k, f"pair {k}")))
                    for k in sorted(shown, key=lambda k: np.nanmin(gaps[:, k]))])
    ax.axhline(0.0, color="k", lw=0.6)
    g = gaps[np.isfinite(gaps)]
    if g.size and g.max() > 0:
        lo = min(float(g.min()), 0.0)
        # a pair far apart would flatten the rest: the top 1 % left out (a geometry's gap is within the reach: all in)
        top = float(g.max()) if per_geometry else float(np.quantile(g, 0.99))
        ax.set_ylim(lo - 0.05 * (g.max() - lo), top * 1.1 + 1e-12)
    more = gaps.shape[1] - len(shown)
    if per_geometry:
        ax.set_ylabel(f"nearest gap [m]\n(within {mm.get('gap_reach', 0):.3g} m)")
        _legend(ax, f"closest {len(shown)} of {gaps.shape[1]} geometries" if more else None)
    else:
        ax.set_ylabel("gap g [m]")
        _legend(ax, f"closest {len(shown)} of {gaps.shape[1]} pairs" if more else None)


def _percussions(ax, _, a, meta, pairs, colour):
    lt, lp, n = a["log_t"], a["log_pair"], a["log_steps"]
    P = a["log_P"] / n  # a row's percussion a step: a stretch of persistent steps' mean (docs/theory.md §5.2)
    if not len(P):
        ax.text(0.5, 0.5, "no percussion logged", transform=ax.transAxes, ha="center")
        ax.set_ylabel("percussion P [N s]")
        return
    ids = np.unique(lp)
    total = np.array([P[lp == k].sum() for k in ids])
    shown = {int(ids[i]) for i in _top(total)}
    # one dot per logged percussion (a resting contact draws its weight x h as a line of dots)
    for k in sorted(ids, key=lambda k: int(k) in shown):
        if int(k) not in shown:
            ax.plot(lt[lp == k], P[lp == k], ".", ms=1.5, color="0.75")
    dots = []
    for k in sorted(shown):
        sel = lp == k
        dots.append((lt[sel], P[sel], dict(marker=".", ls="none", ms=2.5, color=colour.get(k, "0.4"),
                                           label=pairs.get(int(k), f"pair {k}"))))
    for x, y, style in _together(dots, _span(P)):
        ax.plot(x, y, **style)
    # a stretch of persistent steps (a resting contact: its weight x h each step) as a line over its steps
    for k in ids:
        sel = np.flatnonzero((lp == k) & (n > 1))
        if len(sel):
            t1 = lt[sel] + a["log_duration"][sel] * (n[sel] - 1) / n[sel]
            x = np.column_stack([lt[sel], t1, np.full(len(sel), np.nan)]).ravel()
            y = np.column_stack([P[sel], P[sel], np.full(len(sel), np.nan)]).ravel()
            if int(k) in shown:
                name = pairs.get(int(k), f"pair {k}")
                ax.plot(x, y, lw=1.2, color=colour.get(int(k), "0.4"), label=f"{name} at rest (P a step)")
            else:
                ax.plot(x, y, lw=1.2, color="0.75")
    imp = a["log_impact"]
    ax.plot(lt[imp], P[imp], "o", ms=5, mfc="none", mec="k", mew=0.8, label="new impact")
    positive = P[P > 0]
    if positive.size and positive.max() / positive.min() > 100:
        ax.set_yscale("log")  # P > 0 by construction: a plain log axis with its decades labelled
        ax.set_ylim(positive.min() / 2, positive.max() * 2)
    ax.set_ylabel("percussion P [N s]")
    more = len(ids) - len(shown)
    _legend(ax, f"largest {len(shown)} of {len(ids)} pairs and joint limits" if more else None)


def _coordinates(ax, panel, a, meta, pairs, colour):
    x = a[panel]
    names = list(meta.get(f"{panel}_names", [])) or [f"{panel}[{i}]" for i in range(x.shape[1])]
    spread = np.ptp(x, axis=0) if len(x) else np.zeros(x.shape[1])
    shown = set(_top(spread))
    cmap_colours = [f"C{i % 10}" for i in range(len(shown))]
    for i in range(x.shape[1]):
        if i not in shown:
            ax.plot(a["t"], x[:, i], lw=0.5, color="0.75")
    units = list(meta.get(f"{panel}_units", []))
    unit = [units[i] if i < len(units) and units[i] != "?" else None for i in range(x.shape[1])]
    label = [(names[i] if i < len(names) else f"{panel}[{i}]") + (f" [{unit[i]}]" if unit[i] else "")
             for i in range(x.shape[1])]
    _curves(ax, a["t"], [(x[:, i], dict(lw=1.0, color=c, label=label[i])) for c, i in zip(cmap_colours, sorted(shown))])
    drawn = list(dict.fromkeys(unit[i] for i in sorted(shown) if unit[i]))  # the units of the named curves
    word = "q (coordinates)" if panel == "q" else "u (velocities)"
    ax.set_ylabel(f"{word} [{', '.join(drawn)}]" if drawn else word)
    more = x.shape[1] - len(shown)
    _legend(ax, f"{len(shown)} of {x.shape[1]} that move most" if more else None)


def _span(*ys) -> float:
    """The range of the finite values of `ys` (1 if none or all equal)."""
    v = np.concatenate([np.ravel(y) for y in ys]) if ys else np.zeros(0)
    v = v[np.isfinite(v)]
    return float(np.ptp(v)) if v.size and np.ptp(v) > 0 else 1.0


def _together(series, span: float):
    """[(x, y, style)] with the curves that coincide (same x, y within SAME * span everywhere)
    merged into one, drawn in the style of its widest member and labelled with every member's
    name, so that no legend entry names a curve hidden under another."""
    groups: list[list] = []
    for x, y, style in series:
        for g in groups:
            x0, y0, _ = g[0]
            if len(x0) == len(x) and np.array_equal(x0, x) and \
                    np.allclose(y0, y, rtol=0, atol=SAME * span, equal_nan=True):
                g.append((x, y, style))
                break
        else:
            groups.append([(x, y, style)])
    out = []
    for g in groups:
        x, y, style = max(g, key=lambda m: m[2].get("lw", 1.0))
        out.append((x, y, {**style, "label": "\n= ".join(m[2]["label"] for m in g)}))
    return out


def _curves(ax, t, series) -> None:
    """Plot [(y, style)] against t, coinciding curves drawn once under all their names (:func:`_together`)."""
    for x, y, style in _together([(t, y, style) for y, style in series], _span(*[y for y, _ in series])):
        ax.plot(x, y, **style)


def save(traj: Trajectory | str | Path, png: str | Path, panels=DEFAULT_PANELS) -> Path:
    """Draw :func:`figure` and write it to `png`."""
    import matplotlib.pyplot as plt

    fig = figure(traj, panels)
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
