"""Data: the scratch every step reuses (Pinocchio data, coal requests and results, cached
queries, the detection's warm start). One per thread; a run resets it first (Data.reset) and a small model keeps
its runs' Datas for its next runs (spares); the state itself is State."""

from __future__ import annotations

import warnings
from collections import Counter

import coal
import numpy as np
import pinocchio as pin

from .memory import new_data
from .model import Model
from .trees import Kinematics

GJK_TOLERANCE = 1e-12  # coal's GJK/EPA tolerances for the contact normal (default 1e-6 is too coarse)
# Faces parallel to within this [m] over their extent form a contact patch. Coal's EPA normal of
# exactly touching boxes is still ~1e-6 rad off at GJK_TOLERANCE, i.e. ~1e-7 m over 0.1 m: a
# tighter value makes the patch flicker between 1 and 8 points from one step to the next.
PATCH_TOLERANCE = 1e-6
GATE_MARGIN = 1e-6  # [m] see Data: pairs this close are examined (contacts still need g <= tol)


def _pin_box_support() -> None:
    """coal 3.0's Box support function keeps a function-static `inflate`, set once per process by
    the direction of its first call (1 + 1e-10 when that direction has a zero component, else 1):
    box results (5e-12 m on a gap) then depend on which box query a process made first, and a run
    resumed in a new process (checkpoint.py) would part from the uninterrupted one. Make the first
    calls here, at import, along axes (GJK's default guess (1, 0, 0), a ground normal), the value
    most runs set: the same in every process that imports moreau_sim before its first coal query."""
    box, far = coal.Box(1.0, 1.0, 1.0), coal.Transform3s()
    far.setTranslation(np.array([3.0, 0.0, 0.0]))
    coal.distance(box, coal.Transform3s(), box, far, coal.DistanceRequest(), coal.DistanceResult())  # GJK
    coal.collide(box, coal.Transform3s(), coal.Halfspace(np.array([0.0, 0.0, 1.0]), -10.0), coal.Transform3s(),
                 coal.CollisionRequest(), coal.CollisionResult())  # box vs half-space (the swept-sphere support)


_pin_box_support()


class _Held:
    """A value of Data that a compiled Stepper may hold after the step it took (compiled.raw_step): not read back
    from it each step, nor sent to it again at the next, unless something reads it in between. The first read
    converts the Stepper's copy (`read`); assigning a value makes it data's own again. Data's attribute `holder`
    names that Stepper (None: the value is data's)."""

    def __init__(self, read, holder: str):
        self.read, self.holder = read, holder

    def __set_name__(self, owner, name: str) -> None:
        self.slot = "_" + name

    def __get__(self, data, owner=None):
        if data is None:
            return self
        value = getattr(data, self.slot)
        if value is None:
            value = self.read(getattr(data, self.holder))
            self.__set__(data, value)  # data's own now: a change made to it is sent again
        return value

    def __set__(self, data, value) -> None:
        setattr(data, self.slot, value)
        setattr(data, self.holder, None)

    def hold(self, data, stepper) -> None:
        setattr(data, self.slot, None)
        setattr(data, self.holder, stepper)


class Data:
    """Scratch reused by every step: the forest's kinematics (`kinematics`: each tree's Pinocchio
    Data, trees.py), the whole model's Pinocchio data (`pin`, made at first use: the compiled step
    and the adaptive and event-driven integrators), coal results, cached queries, and the
    detection's warm start `warm_start_pairs`, the pairs that had contacts at the last detection
    (it keeps a resting pair examined when coal's narrow phase misses it for a step,
    contacts._near_polytopes).

    Create one per thread with :func:`make_data`; a run starts by resetting it (reset), so a run's steps do not
    depend on what ran on its Data before. The state itself is in State."""

    # read from the compiled Stepper that holds them (hold_warm_start, hold_active) at the first read
    warm_start_pairs = _Held(lambda stepper: set(stepper.warm), "warm_start_holder")
    active_rows = _Held(lambda stepper: frozenset(map(tuple, stepper.active)), "active_holder")

    def __init__(self, model: Model):
        self._model = model
        self._pin = None
        where = str(model.scene.path) if model.scene.path else model.scene.name
        self.kinematics = Kinematics(model.forest, make=lambda m: new_data(m, f"{where} (a body of it)", checked=True))
        tol = model.options.contact_tolerance
        self._geom = None
        self._coal: dict[int, tuple] = {}  # pair -> (request, result, coal functor): a PairTable's pairs (collide)
        self._coal_distance: dict[int, tuple] = {}  # the same for their distances (distance)
        if model.listed:
            self._make_geom()
            self.oMg = self._geom.oMg  # the geometries' world placements (trees.Forest.place)
        else:  # many pairs: no GeometryData of them all unless something asks for it (geom)
            self.oMg = [pin.SE3.Identity()] * len(model.geometries)
        self.box_edges: dict = {}  # geometry index -> its box's 12 edges in the joint frame (contacts, filled lazily)
        # the detection's warm start: the pairs with contacts at the last detection (contacts._near_polytopes); where
        # a compiled step made it, the compiled Stepper holds it until it is read (warm_start_pairs, hold_warm_start)
        self.warm_start_pairs = set()
        # the projection's warm start above qp.SPARSE_ROWS rows: the identities (pair, kind, feature) of the rows of
        # the last step's final active set (its first pass's; piqp's answer: lam > 0), where it had more rows than
        # that; else empty (stepper.keep_active, docs/theory.md §1.3)
        # (a compiled Stepper holds the set it kept until the set is read: active_rows, hold_active)
        self.active_rows = frozenset()
        self.patch_request = coal.ContactPatchRequest()
        self.patch_request.setPatchTolerance(PATCH_TOLERANCE)
        self.patch_collision = coal.CollisionResult()
        self.patch_result = coal.ContactPatchResult(self.patch_request)
        self.fallback_request = coal.CollisionRequest()  # coal's default GJK/EPA tolerances
        self.fallback_request.security_margin = tol
        self.fallback_request.enable_contact = True
        self.fallback_result = coal.CollisionResult()
        self.point = coal.Sphere(0.0)  # a vertex, for point-vs-shape signed distances
        self.point_tf = coal.Transform3s()
        self.distance_request = coal.DistanceRequest()
        self.distance_result = coal.DistanceResult()
        self._point_queries: dict[int, coal.ComputeDistance] = {}
        self.shapes = [g.geometry for g in model.geometries]
        # steps of this Data's runs by the way they went: "flight", "contact", "python: <reason>" (compiled.counts)
        self.step_counts: Counter = Counter()

    def reset(self, guesses=None) -> "Data":
        """Bring back what a run carries from one step to the next to a new Data's (docs/theory.md §2.8, "A run
        starts from a fresh Data"): the detection's and the projection's warm starts, coal's cached GJK guesses
        (every request and result), the pairs' and points' coal queries of a PairTable (made again at first use)
        and the compiled Stepper (made again at the next compiled step; `step_counts` stay: they count this Data's
        runs). The Pinocchio Datas are kept: scratch that every algorithm writes before it reads. A run given this
        Data then takes the same steps, bit for bit, as on a new one, whatever ran on it before. guesses: the
        compiled reset of coal's guesses (compiled.guess_reset: requests, results and the GeometryData's functors
        at C++ speed), else Python's (requests and results: the functors' own hints, a protected member, are then
        kept; they are not read where a request enables its cached guess, as pinocchio's do). Returns self."""
        self.__dict__.pop("_compiled_step", None)
        self.warm_start_pairs = set()
        self.active_rows = frozenset()
        g = self._geom
        requests, results = [self.fallback_request, self.distance_request], [self.patch_collision,
                                                                            self.fallback_result, self.distance_result]
        if guesses is not None:
            guesses(g, requests, results)
        else:
            if g is not None:
                requests += [*g.collisionRequests, *g.distanceRequests]
                results += [*g.collisionResults, *g.distanceResults]
            for holders, fresh in ((requests, _FRESH_REQUEST), (results, _FRESH_RESULT)):
                for h in holders:
                    h.cached_gjk_guess, h.cached_support_func_guess = fresh
        self._coal.clear()
        self._coal_distance.clear()
        self._point_queries.clear()
        return self

    def hold_warm_start(self, stepper) -> None:
        """The detection's warm start is the one the compiled Stepper `stepper` holds after its step (_Held)."""
        Data.warm_start_pairs.hold(self, stepper)

    def hold_active(self, stepper) -> None:
        """The projection's warm start is the set the compiled Stepper `stepper` kept at its step (_Held)."""
        Data.active_rows.hold(self, stepper)

    def _make_geom(self) -> None:
        model = self._model
        # GeometryData must be created after every geometry and pair exists (segfault otherwise).
        self._geom = pin.GeometryData(model.geom)
        # proxies of the pairs' distance results, made once: they read the live results after each
        # computeDistances (contacts.pair_distances), where indexing the vector anew costs ~1 us a pair
        self.distance_results = list(self._geom.distanceResults)
        for req in self._geom.collisionRequests:
            _gate(req, model.options.contact_tolerance)
        for preq in self._geom.contactPatchRequests:
            preq.setPatchTolerance(PATCH_TOLERANCE)

    @property
    def geom(self) -> pin.GeometryData:
        """Pinocchio's GeometryData of every pair (coal requests and results, placements oMg): made with
        the Data for a model whose pairs are listed, else at first use (the compiled step, distances of
        every pair, the swept test), when its placements are its own, not oMg's."""
        if self._geom is None:
            self._make_geom()
        return self._geom

    def collide(self, k: int) -> bool:
        """coal's collision query of pair k at the placements oMg (after fresh_guesses on its request):
        pin.computeCollision's for a listed model; else the same query on coal directly (the same
        request settings, pinocchio's distance_upper_bound, a cleared result, coal's functor)."""
        model = self._model
        if model.listed:
            return pin.computeCollision(model.geom, self._geom, k)
        req, res, f = self.pair_query(k)
        p = model.pairs[k]
        req.distance_upper_bound = req.security_margin + 1e-6  # as pinocchio's computeCollision
        res.clear()
        f(coal.Transform3s(self.oMg[p.first]), coal.Transform3s(self.oMg[p.second]), req, res)
        return res.isCollision()

    def collision_request(self, k: int) -> coal.CollisionRequest:
        return self._geom.collisionRequests[k] if self._model.listed else self.pair_query(k)[0]

    def collision_result(self, k: int) -> coal.CollisionResult:
        return self._geom.collisionResults[k] if self._model.listed else self.pair_query(k)[1]

    def pair_query(self, k: int) -> tuple:
        """(request, result, coal.ComputeCollision) of pair k of a PairTable, made at its first query as
        pinocchio's GeometryData makes them (CollisionRequest(NO_REQUEST, 1), cached GJK guess) and gated."""
        out = self._coal.get(k)
        if out is None:
            p, shapes = self._model.pairs[k], self.shapes
            req = coal.CollisionRequest(coal.CollisionRequestFlag.NO_REQUEST, 1)
            with warnings.catch_warnings():  # coal deprecates the flag pinocchio's GeometryData sets
                warnings.simplefilter("ignore", DeprecationWarning)
                req.enable_cached_gjk_guess = True
            _gate(req, self._model.options.contact_tolerance)
            f = coal.ComputeCollision(shapes[p.first], shapes[p.second])
            out = self._coal[k] = (req, coal.CollisionResult(), f)
        return out

    def distance(self, k: int) -> float:
        """coal's signed distance [m] of pair k of a PairTable at the placements oMg: pin.computeDistance's
        query on coal directly (the request pinocchio's GeometryData makes, a cleared result)."""
        req, res, f = self.distance_query(k)
        p = self._model.pairs[k]
        res.clear()
        f(coal.Transform3s(self.oMg[p.first]), coal.Transform3s(self.oMg[p.second]), req, res)
        return res.min_distance

    def distance_query(self, k: int) -> tuple:
        """(request, result, coal.ComputeDistance) of pair k of a PairTable, made at first use."""
        out = self._coal_distance.get(k)
        if out is None:
            p, shapes = self._model.pairs[k], self.shapes
            req = coal.DistanceRequest(True)
            with warnings.catch_warnings():  # coal deprecates the flag pinocchio's GeometryData sets
                warnings.simplefilter("ignore", DeprecationWarning)
                req.enable_cached_gjk_guess = True
            f = coal.ComputeDistance(shapes[p.first], shapes[p.second])
            out = self._coal_distance[k] = (req, coal.DistanceResult(), f)
        return out

    @property
    def pin(self) -> pin.Data:
        """The whole model's Pinocchio Data, made at first use; a SceneError naming its size when it
        exceeds the memory limit (memory.check_data_size: Pinocchio 4.1's Data is nv^3)."""
        if self._pin is None:
            model = self._model
            where = str(model.scene.path) if model.scene.path else model.scene.name
            self._pin = new_data(model.pin, f"{where} ({len(model.bodies)} bodies)")
        return self._pin

    def _guess_holders(self) -> list:
        """Every coal request and result that carries a GJK guess from one call to the next, but a PairTable's pairs'
        (_table_holders: made per pair at its first query, not a GeometryData of every pair)."""
        fixed = [self.patch_collision, self.fallback_request, self.fallback_result, self.distance_request,
                 self.distance_result]
        if not self._model.listed:
            return fixed
        g = self.geom
        return [*g.collisionRequests, *g.collisionResults, *g.distanceRequests, *g.distanceResults, *fixed]

    def _table_holders(self) -> dict:
        """{"collision" | "distance": {pair: (request, result)}}: the coal objects of a PairTable's pairs queried so
        far (pair_query, distance_query)."""
        return {"collision": {k: v[:2] for k, v in self._coal.items()},
                "distance": {k: v[:2] for k, v in self._coal_distance.items()}}

    def warm_start(self) -> dict:
        """What the next detection starts from, as JSON-able lists: warm_start_pairs and coal's
        cached GJK guesses (requests keep enable_cached_gjk_guess, coal's default); for a model without a pair
        list, those of each pair queried so far ("table": pair, then the request's and the result's guess and
        support hint). Restoring it (restore_warm_start) makes a new Data continue bit for bit (checkpoint.py)."""
        holders = self._guess_holders()
        out = {"pairs": sorted(self.warm_start_pairs),
               "gjk_guess": [h.cached_gjk_guess.tolist() for h in holders],
               "support_guess": [h.cached_support_func_guess.tolist() for h in holders]}
        if not self._model.listed:
            out["table"] = {kind: [[k] + [x for h in pair for x in (h.cached_gjk_guess.tolist(),
                                                                     h.cached_support_func_guess.tolist())]
                                   for k, pair in sorted(queries.items())]
                            for kind, queries in self._table_holders().items()}
        return out

    def restore_warm_start(self, warm: dict) -> None:
        self.warm_start_pairs = set(warm["pairs"])
        for h, guess, support in zip(self._guess_holders(), warm["gjk_guess"], warm["support_guess"], strict=True):
            h.cached_gjk_guess = np.array(guess, float)
            h.cached_support_func_guess = np.array(support, np.int32)
        make = {"collision": self.pair_query, "distance": self.distance_query}
        for kind, rows in warm.get("table", {}).items():  # each pair's objects made as its first query makes them
            for k, req_g, req_s, res_g, res_s in rows:
                req, res = make[kind](int(k))[:2]
                req.cached_gjk_guess, req.cached_support_func_guess = np.array(req_g, float), np.array(req_s, np.int32)
                res.cached_gjk_guess, res.cached_support_func_guess = np.array(res_g, float), np.array(res_s, np.int32)

    def point_query(self, g: int) -> coal.ComputeDistance:
        """Cached coal functor: signed distance from a point to geometry g."""
        f = self._point_queries.get(g)
        if f is None:
            f = self._point_queries[g] = coal.ComputeDistance(self.point, self.shapes[g])
        return f


# coal's cached guesses of a new request and of a new result (a GJK warm start and a support hint): what Data.reset
# gives back to every request and result it keeps
_FRESH_REQUEST = (coal.CollisionRequest().cached_gjk_guess, coal.CollisionRequest().cached_support_func_guess)
_FRESH_RESULT = (coal.CollisionResult().cached_gjk_guess, coal.CollisionResult().cached_support_func_guess)


def _gate(req: coal.CollisionRequest, tol: float) -> None:
    """The detection's settings of a pair's collision request (tol: the contact tolerance [m])."""
    # gate of the active set: a pair is examined when coal puts it within GATE_MARGIN (its
    # contacts are then kept where g <= tol); coal's narrow phase misses exactly touching
    # coplanar boxes now and then at a margin of 1e-9 m (gap -5e-12 reported as apart)
    req.security_margin = max(tol, GATE_MARGIN)
    req.num_max_contacts = 1
    req.enable_contact = True  # normal, depth and witness points (EPA when penetrating)
    # GJK/EPA default tolerances (1e-6) tilt the normal of exactly touching boxes by ~5 deg
    req.gjk_tolerance = req.epa_tolerance = GJK_TOLERANCE


def make_data(model: Model) -> Data:
    return Data(model)


def spares(model: Model) -> list:
    """The Datas that finished runs of `model` handed back for its next runs: the runs' own (driver.run_data, reset
    before use) and their checks' (invariants.Invariants.data: a Data's energies are functions of (q, u) alone,
    whatever it evaluated before). A Data in use is no other run's (list pop/append: one thread at a time). Kept on
    the model itself, not in a weak-keyed table: a Data refers to its model, so a table's entry would keep every
    model it saw alive; on the model the cycle goes with it."""
    return model.__dict__.setdefault("_spare_datas", [])
