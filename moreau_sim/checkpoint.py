"""Checkpoints of a run (any integrator), and resuming from one bit-identically (docs/output.md).

    ms.run("scenes/zeno_ball.toml", duration=1000, checkpoint="ball.checkpoint.npz",
           checkpoint_every=100.0, resume=True)

A checkpoint is a trajectory NPZ (trajectory.py, written atomically) of the samples, percussion
log and branches so far, whose meta["checkpoint"] holds everything else carried from one
accepted point to the next: the integrator's state (its state_dict(), protocol.py), the
driver's (driver.py: the contact work and correction energy since the last sample, the next
grid instant, the last step's contacts), the recorder's running ledger terms (Recorder.carried)
and the detection's warm start (Data.warm_start: the pairs it examines, coal's cached GJK guesses).
JSON keeps floats exactly (shortest repr), so the resumed run takes the same steps on the same
numbers as an uninterrupted one.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path


from .data import Data
from .errors import SceneError
from .model import Model
from .recording import Recorder
from .trajectory import read_npz, verify_checksum

KEY = "checkpoint"


@dataclass(frozen=True, kw_only=True)
class Checkpoint:
    """Where and how often a run saves its checkpoint.

    path: the checkpoint NPZ; every [s of simulated time]: save at the first accepted point (a
    step, an event) at least this long after the previous checkpoint, None: never; resume: continue from
    `path` when it exists (it must come from the same scene, URDFs and options); keep: leave the
    file when the run completes (the CLI removes it itself once the output is saved)."""

    path: Path
    every: float | None = None
    resume: bool = False
    keep: bool = False

    def __post_init__(self):
        e = self.every
        if e is not None and not (isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e)
                                  and e > 0):
            raise SceneError(f"checkpoint_every: must be a finite time > 0 s, got {e!r}")


def identity(model: Model) -> dict:
    """What must match for a checkpoint to resume this run: the scene's TOML and URDF texts, options."""
    sc = model.scene
    return json.loads(json.dumps({"toml": sc.source, "urdf": {b.name: Path(b.urdf).read_text(encoding="utf-8")
                                                                for b in sc.bodies},
                                  "options": model.options.to_dict()}))


def save(path: Path, rec: Recorder, meta: dict, *, integ, loop: dict, data: Data) -> None:
    """Write the checkpoint at the integrator's current accepted point (atomically: a reader sees
    the old or the new one); integ: the integrator (protocol.Integrator), loop: the driver's state."""
    state = integ.state
    meta = {**meta, KEY: {"steps": integ.position()[0] - 1, "t": state.t, "integrator": integ.state_dict(),
                          "loop": loop, "warm_start": data.warm_start(), "recorder": rec.carried(state),
                          "identity": identity(rec.model)}}
    rec.trajectory(meta, final=False).save(path)


def load(path: Path, model: Model, rec: Recorder, data: Data, integ) -> tuple[dict, float, float]:
    """Restore `integ`, `rec` and `data` from the checkpoint at `path`, the recorder one array at
    a time (a spilling recorder writes each to its file: a resumed run needs no more memory than
    the first); returns (the driver's state, the wall and CPU time so far [s]). SceneError naming the
    file when it is damaged or belongs to another run."""
    try:
        with read_npz(path) as z:
            meta = json.loads(str(z["meta"]))
            verify_checksum(path, meta, z)
            ck = meta.get(KEY)
            if not isinstance(ck, dict):
                raise SceneError(f"{path}: not a checkpoint (no meta.{KEY})")
            if ck.get("identity") != identity(model):
                raise SceneError(f"{path}: a checkpoint of another run (its scene, URDFs or options differ); "
                                 "delete it or resume with the same settings")
            integ.load_state_dict(ck["integrator"])
            rec.restore(z, ck["recorder"], integ.state)
    except SceneError:
        raise
    except ValueError as exc:
        raise SceneError(f"{exc}; delete it to start again") from None
    data.restore_warm_start(ck["warm_start"])
    run = meta.get("run", {})
    return ck["loop"], float(run.get("wall_seconds") or 0.0), float(run.get("cpu_seconds") or 0.0)
