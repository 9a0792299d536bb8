"""Benchmarks of moreau-sim: exact references, error metrics, the peer simulators, and the
benchmark drivers behind scripts/*.py. Benchmarks are measurements, not tests: they never fail on
a bad number, and nothing here asserts a time.

Modules:
- references: the exact references of the bundled scenes (ball impact times / apexes / Zeno time
  and rest bound, touching and gapped cradle, corner point outcomes) - the one home of each formula.
- metrics: error metrics between a trajectory and a reference (impact times, apexes, state, energy,
  penetration).
- spec: the neutral scene spec every peer runner reads (spheres and boxes on free or slide joints,
  half-space and box statics), built from a moreau-sim model, and the way back to its coordinates.
- peers: MuJoCo, PyBullet and Siconos, one runner each (peers.mujoco / .pybullet / .siconos, each
  with its documented DEFAULTS), `available()` and `run()` / `run_model()`.
- work_precision: error against exact references vs CPU time, for moreau-sim and the peers
  (scripts/work_precision.py).
- stability: the stress suite side by side (scripts/stability.py).
- step_costs: the cost of one step split into dynamics, collision, QP and glue (scripts/bench_step.py).
- check_peers: every available peer against the exact references (scripts/check_peers.py).
- corner_branches, plot_sweep: figures (scripts/corner_branches.py, scripts/plot_sweep.py).

Every driver writes to out/ by default; `--out docs/bench` (work_precision, bench_step) or
`--out docs/stability.md` (stability) regenerates the committed files.

Peers, install:

    pip install -e '.[peers]'                 # MuJoCo, PyBullet (or a venv of their own: $PEERS_PYTHON)
    apt-get install -y python3-siconos        # Siconos: Debian's Python only (peers.SICONOS_PYTHON)

Peer settings (each runner's module doc has the details and why):
- MuJoCo: soft contacts, solref "-k -b" with constant impedance 0.95, sqrt(k) = omega_h / h with
  omega_h = 0.2, damping from the Schwager-Poschel map for e, condim 1, Euler, Newton solver, 100
  iterations, tolerance 1e-10, stepped by mujoco.rollout.
- PyBullet: every body and static at restitution sqrt(e) (a pair multiplies them), no friction or
  damping, no sleeping; config "default" (Bullet's defaults: restitution threshold 0.2 m/s,
  speculative contacts within 0.02 m, contact ERP) or "tuned" (those three at 0). Bullet keeps
  contactBreakingThreshold process-global, so the runner always sets it.
- Siconos: MoreauJeanOSI(1/2), NewtonImpactNSL(e), one LCP per step (Lemke); spheres on collinear
  slide joints (gaps exactly as the floating-point positions give them, or exact_gaps=True), and
  one free box over the ground through its Bullet mechanics (NewtonImpactFrictionNSL with mu = 0).
CPU time is time.process_time() around each peer's stepping loop only (MuJoCo a C rollout,
PyBullet and Siconos through their Python bindings: not apples to apples).
"""

from __future__ import annotations

from pathlib import Path

REPO = Path(__file__).resolve().parents[2]  # the source tree (editable install): scenes/, docs/
SCENES = REPO / "scenes"
OUT = Path("out")  # default output folder of every driver, relative to the current directory


def scene_path(name: str) -> Path:
    """The bundled scene file scenes/<name>.toml."""
    return SCENES / f"{name}.toml"
