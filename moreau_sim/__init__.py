"""moreau-sim: rigid multibody impacts with Glocker's Newtonian impact law (global
restitution e) in a midpoint Moreau time-stepper, on Pinocchio + coal + piqp.

    import moreau_sim as ms
    traj = ms.run("scenes/bouncing_ball.toml", dt=1e-3, restitution=0.8)
"""

from .contacts import Contacts, contact_rows, detect, pair_distances
from .errors import MoreauSimError, SceneError, SimulationError
from .law import Impact, impact, outcome, project
from .model import Data, Model, build_model, initial_state, make_data
from .qp import QPResult
from .scene import (Bias, Integrator, Options, PositionCorrection, QPForm, RootJoint, Scene, Separating,
                    SlowImpacts, load_scene, parse_scene)
from .simulate import run, simulate, summary
from .state import State
from .stepper import StepResult, step
from .trajectory import Trajectory, load_trajectory
from .outcomes import Outcome, impact_outcomes

__version__ = "0.1.0"

__all__ = [
    "Bias", "Contacts", "Data", "Impact", "Integrator", "Model", "Outcome", "PositionCorrection", "SlowImpacts", "MoreauSimError", "Options", "QPForm", "QPResult", "RootJoint",
    "Scene", "SceneError", "Separating", "SimulationError", "State", "StepResult", "Trajectory", "build_model",
    "contact_rows", "detect", "impact", "impact_outcomes", "initial_state", "load_scene", "load_trajectory", "make_data",
    "outcome", "pair_distances", "parse_scene", "project", "run", "simulate", "step", "summary",
]
