"""moreau-sim: rigid multibody impacts with Glocker's Newtonian impact law (global
restitution e) in a midpoint Moreau time-stepper, on Pinocchio + coal + piqp.

    import moreau_sim as ms
    traj = ms.run("scenes/bouncing_ball.toml", dt=1e-3, restitution=0.8)

Each name below has one home (its module); this namespace re-exports the public ones.
"""

import sys as _sys

if _sys.argv[0:1] and _sys.argv[0].endswith("moreau-sim") and "multiprocessing" not in _sys.modules:
    # the console script (not a sweep's worker): Ctrl-C or SIGTERM during the imports below is one line
    from .interrupts import during_startup as _during_startup

    _during_startup()

from .builder import SceneBuilder
from .constraints import Constraints, assemble_constraints, contact_rows
from .contacts import Contacts, FeatureKind, detect, pair_distances
from .data import Data, make_data
from .errors import MoreauSimError, SceneError, SimulationError
from .event_driven import UnsupportedModel, simulate_event_driven
from .law import Impact, impact, outcome, percussion, project
from .ledger import Ledger, ledger
from .model import Model, build_model, initial_state
from .options import (Bias, Integrator, MeshMode, Options, PositionCorrection, QPForm, RootJoint, Selection,
                      Separating, SlowImpacts, StaticShape, Tunnelling)
from .outcomes import Outcome, impact_outcomes
from .qp import QPResult
from .recording import Recorder
from .scene import Scene, load_scene, parse_scene
from .simulate import run, simulate, summary
from .state import State
from .results import StepResult
from .stepper import (ContactProblem, ImpactSolution, StepView, assemble, correct_positions, solve_impact, step,
                      step_in_place)
from .trajectory import Trajectory, load_trajectory

__version__ = "0.1.0"

__all__ = [
    "Bias", "ContactProblem", "Constraints", "Contacts", "Data", "FeatureKind", "Impact", "ImpactSolution",
    "Integrator", "Ledger", "MeshMode", "Model", "MoreauSimError", "Options", "Outcome", "PositionCorrection", "QPForm",
    "QPResult", "Recorder", "RootJoint", "Scene", "SceneBuilder", "SceneError", "Selection", "Separating",
    "SimulationError", "SlowImpacts", "State", "StaticShape", "StepResult", "StepView", "Trajectory", "Tunnelling",
    "UnsupportedModel",
    "assemble", "assemble_constraints", "build_model", "contact_rows", "correct_positions", "detect", "impact",
    "impact_outcomes", "initial_state", "ledger", "load_scene", "load_trajectory", "make_data", "outcome",
    "pair_distances", "parse_scene", "percussion", "project", "run", "simulate", "simulate_event_driven",
    "solve_impact", "step", "step_in_place", "summary",
]
