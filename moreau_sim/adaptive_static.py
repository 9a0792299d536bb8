"""What an adaptive run reads of its model alone, made once per model and shared by its runs (a model is never
modified after build_model; docs/theory.md §8): the features it locates events on, the compiled extrapolated
step at given tolerances, and the model's static figures (Static). Each table is weak-keyed by its model and
holds no reference to it."""

from __future__ import annotations

import weakref

import numpy as np
import pinocchio as pin

from . import compiled_events
from .event_rules import model_features
from .gaps import UnsupportedModel
from .model import Model

FIXED_POINT = 1e-3  # the midpoint bias's fixed point is iterated to this fraction of the step tolerance
MAX_FEATURES = 64  # more features than box pairs' (very many contacts): fixed steps throughout

_FEATURES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> features_of(model)
_EXTRAPOLATORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> {(seq, ..., atol): step}


def features_of(model: Model) -> tuple[tuple, str | None]:
    """(the features an adaptive run of `model` locates events on, why none: None where it does), made once per model
    (a model is never modified after build_model): event_rules.model_features but cylinders on boxes and more than
    MAX_FEATURES features not counting box pairs'."""
    got = _FEATURES.get(model)
    if got is not None:
        return got
    try:
        feats, why = model_features(model), None
    except UnsupportedModel as exc:
        feats, why = (), str(exc)
    names = {p.index: p.name for p in model.pairs}
    cyl_box = sorted({names[f.pair] for f in feats if f.kind in ("rim_box", "side_edge")})
    if cyl_box:  # their stand-ins and screening jump (docs/theory.md §7.2): the event-driven integrator's only
        feats, why = (), f"cylinder vs box pairs ({', '.join(cyl_box[:3])}): event-driven only"
    n = sum(f.box is None for f in feats)
    if n > MAX_FEATURES:
        feats, why = (), f"{n} features (not counting box pairs') > MAX_FEATURES = {MAX_FEATURES}"
    got = _FEATURES[model] = (feats, why)
    return got


def extrapolator_of(model: Model, seq: tuple, ratios: tuple, lie: bool, rtol: float, atol: float):
    """compiled_events.extrapolator, made once per model and tolerances: the compiled step keeps nothing from one
    call to the next (its Pinocchio Data is scratch), so the runs of one model share it."""
    key = (seq, ratios, lie, rtol, atol)
    made = _EXTRAPOLATORS.setdefault(model, {})
    if key not in made:
        made[key] = compiled_events.extrapolator(model, seq=seq, ratios=ratios, lie=lie, rtol=rtol, atol=atol,
                                                 fixed_point=FIXED_POINT)
    return made[key]




class Static:
    """What an adaptive run reads of its model and features alone, made once per model (static_of): lie (a joint with
    nq != nv), neutral (pin.neutral, read-only), flat (_size: a vector space whose neutral is 0), is_box (which
    features are box pairs'), any_box, box_half (the smallest half side of their boxes [m]), far (k -> _End.near of
    k compiled features, AdaptiveRun._far)."""

    __slots__ = ("feats", "lie", "neutral", "flat", "is_box", "any_box", "box_half", "far")

    def __init__(self, model: Model, feats: tuple):
        pm = model.pin
        self.feats = feats
        self.lie = any(pm.joints[j].nq != pm.joints[j].nv for j in range(1, pm.njoints))
        self.neutral = pin.neutral(pm)
        self.neutral.flags.writeable = False
        self.flat = not self.lie and not self.neutral.any()
        self.is_box = np.array([f.box is not None for f in feats], bool)
        self.is_box.flags.writeable = False
        self.any_box = bool(self.is_box.any())
        self.box_half = min([min(f.box.a.half, f.box.b.half) for f in feats if f.box is not None], default=np.inf)
        self.far: dict = {}


_STATICS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # model -> Static of its run's features


def static_of(model: Model, feats: tuple) -> Static:
    """The Static of `model` on `feats`, made once per model and features (a model is never modified after
    build_model; its runs share it: nothing in it is written to but far's entries, each made once)."""
    got = _STATICS.get(model)
    if got is None or got.feats is not feats:
        got = _STATICS[model] = Static(model, feats)
    return got
