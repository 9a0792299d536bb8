// moreau_sim._step.Runner: the time-stepping run loop in C++ (moreau_sim/compiled_run.py; docs/theory.md §2.8, §9).
// Included by step.cpp after its Stepper (the same extension, the same translation unit): it loops the compiled
// step and records into the columns Python hands it (recording._Columns), mirroring operation by operation, in the
// same order, what the Python run does per step (time_stepping.TimeStepping.step, driver._Loop.account):
// recording.Recorder.log_percussions, .account_step (ledger.impact_terms's products summed in index order as
// sums.ordered sums them: odot, docs/theory.md §2.8), .sample (contacts.pair_distances on the forest, trees.Forest's
// energies), and invariants.Invariants's "sample" and "point" checks. Every figure it carries between steps comes
// in from the Python objects and goes back to them at each return (carry()), so that checkpoints, interrupts and
// the Python step in between see exactly the Python run's state. A step it cannot finish as the Python run would
// (the compiled step's FALLBACK, a non-finite state or energy, an undefined gap, a check that fires) is undone
// (nothing committed; the detection's carried state restored: Undo) and handed back: the Python run takes that one
// step, with its messages and errors.
#include <nanobind/ndarray.h>
#include <nanobind/stl/array.h>
#include <nanobind/stl/pair.h>

#include <pinocchio/algorithm/kinematics.hpp>

#include "actuation.hpp"

#include <array>
#include <chrono>
#include <cstring>

namespace run_loop {

// Why Runner.advance returned (moreau_sim._step.Stop)
enum class Stop { FINISHED, POLL, CHECKPOINT, FULL, HAND_BACK };

// one column of a _Columns group: its data and the length of one row
template <class T> struct Col {
  T *p = nullptr;
  int64_t row = 1;
  T *at(int64_t i) const { return p + i * row; }
};
template <class T> Col<T> column(const nb::dict &d, const char *name) {
  auto a = nb::cast<nb::ndarray<T, nb::c_contig, nb::device::cpu>>(d[name]);
  Col<T> c;
  c.p = a.data();
  for (size_t k = 1; k < a.ndim(); ++k) c.row *= (int64_t)a.shape(k);
  return c;
}

}  // namespace run_loop
using run_loop::Col;
using run_loop::Stop;

// The forest's figures as trees.Forest and contacts.pair_distances compute them: kinetic and potential energy and
// the pairs' distances at a state, on the forest's own Pinocchio Datas (src/forest.hpp) and the Stepper's
// GeometryData (the Python run's, data.geom). One home for what a sample records (recording.Recorder.sample): the
// Runner below and adaptive.hpp's DenseSampler.
class ForestFigures {
 public:
  using TreeArgs = Forest::TreeArgs;
  // trees: (pin.Model, pin.Data, q start, nq, v start, nv) per tree of the forest (trees.Forest, its Kinematics'
  // datas); tree_of_joint, local_joint: the forest's maps
  ForestFigures(Stepper &S, const TreeArgs &trees, std::vector<int64_t> tree_of_joint, std::vector<int64_t> local_joint)
      : S_(S), forest_(trees, std::move(tree_of_joint), std::move(local_joint)) {}
  double kinetic(const VectorXd &q, const VectorXd &u) { return forest_.kinetic(q, u); }  // Forest.kinetic
  double potential(const VectorXd &q) { return forest_.potential(q); }  // Forest.potential
  size_t pairs() const { return S_.gm_.collisionPairs.size(); }
  // Model.gaps_per_geometry (Stepper::gap_reach): its gaps are one per geometry, +inf where none is near
  bool per_geometry() const { return S_.gaps_per_geometry_; }
  // the sample's gaps into `out` (recording.Recorder.sample, contacts.record_gaps): contacts.geometry_gaps, or
  // contacts.pair_distances (Forest.place with the geometry placements, then coal's distances)
  void gaps(const VectorXd &q, double *out) {
    if (per_geometry()) S_.geometry_gaps(q, out);
    else if (!S_.gm_.collisionPairs.empty()) S_.distances(q, out);
  }

 private:
  Stepper &S_;
  Forest forest_;
};

class Runner {
 public:
  // stepper: the run's compiled Stepper; trees: (pin.Model, pin.Data, q start, nq, v start, nv) per tree of the
  // forest (trees.Forest, its Kinematics' datas); tree_of_joint, local_joint: the forest's maps; constants: the
  // Python run's (by name); torques: the model's joint torques (src/actuation.hpp's Actuation), None: none
  Runner(nb::object stepper, std::vector<std::tuple<nb::object, nb::object, int64_t, int64_t, int64_t, int64_t>> trees,
         std::vector<int64_t> tree_of_joint, std::vector<int64_t> local_joint,
         const std::map<std::string, double> &constants, bool checks, nb::object torques)
      : py_stepper_(stepper), S_(nb::cast<Stepper &>(stepper)),
        forest_(S_, trees, std::move(tree_of_joint), std::move(local_joint)), checks_(checks) {
    if (!torques.is_none()) act_.emplace(nb::cast<nb::tuple>(torques));
    auto get = [&](const char *k) {
      auto it = constants.find(k);
      if (it == constants.end()) throw nb::value_error((std::string("constant missing: ") + k).c_str());
      return it->second;
    };
    log_relative_ = get("log_relative"), acceleration_ = get("acceleration"), gap_round_off_ = get("gap_round_off");
    persist_ = (int64_t)get("persist"), rel_ = get("rel"), rel_ledger_ = get("rel_ledger"), tol_ = get("tol");
    g_ = get("g");
    guard_ = S_.boxes_;  // pairs of two boxes: their detection carries state from step to step (Undo)
    rest_accuracy_ = get("rest_accuracy");
  }

  // Steps k+1.. of n (h, e; t0 the run's start, every: save_every) from (t, q, u) at most until a step ends at
  // t >= t_stop, wall_budget seconds have passed, a group of columns has no room (rooms: rows free from starts,
  // samples / log / impacts), or a step must go to Python.
  Stop advance(double t, VectorXd q, VectorXd u, int64_t k, int64_t n, int64_t every, double h, double e, double t0,
               double t_stop, double wall_budget, nb::dict samples, nb::dict log, nb::dict impacts,
               std::array<int64_t, 3> starts, std::array<int64_t, 3> rooms) {
    bind(samples, log, impacts);
    written_ = {0, 0, 0};
    flight_ = contact_ = 0;
    const auto wall0 = std::chrono::steady_clock::now();
    t_ = t, q_ = std::move(q), u_ = std::move(u), k_ = k;
    for (int64_t done = 0;; ++done) {
      if (k_ >= n) return Stop::FINISHED;
      log_room_ = rooms[1] - written_[1];
      if (rooms[0] - written_[0] < 1 || log_room_ < log_need_ || rooms[2] - written_[2] < 1) return Stop::FULL;
      full_ = false;
      if (!step(k_, n, every, h, e, t0, starts)) return full_ ? Stop::FULL : Stop::HAND_BACK;
      if (k_ >= n) return Stop::FINISHED;
      if (t_ >= t_stop) return Stop::CHECKPOINT;
      if ((done & 63) == 63 &&
          std::chrono::duration<double>(std::chrono::steady_clock::now() - wall0).count() >= wall_budget)
        return Stop::POLL;
    }
  }

  // the figures carried between steps (Recorder, _Loop, Invariants), by name
  std::map<std::string, double> carry() const { return c_.as_dict(); }
  void load(const std::map<std::string, double> &d, std::vector<std::array<int64_t, 3>> previous,
            std::vector<std::pair<int64_t, double>> held) {
    c_.from(d);
    c_.previous = std::move(previous);
    c_.held.assign(held.begin(), held.end());
  }
  std::vector<std::array<int64_t, 3>> previous() const { return c_.previous; }
  // the most log rows one step has written or asked for (compiled_run.py reserves at least this many a call)
  int64_t log_need() const { return log_need_; }
  std::vector<std::pair<int64_t, double>> held() const { return c_.held; }
  // (t, q, u, steps done) after the last step taken (new arrays)
  std::tuple<double, VectorXd, VectorXd, int64_t> where() const { return {t_, q_, u_, k_}; }
  std::array<int64_t, 3> written() const { return written_; }
  std::pair<int64_t, int64_t> counts() const { return {flight_, contact_}; }

 private:
  // What the Python run carries from one step to the next (the attribute each mirrors in brackets)
  struct Carry {
    // Recorder: _smooth, _diss, _law, _E, _TV, _new_impact, _rise, _law_difference, _contact_steps, smooth_deficit
    double smooth = 0, diss = 0, law = 0, E = 0, T = 0, V = 0, rise = 0, t_rise = 0, law_diff = 0, t_law_diff = 0;
    double new_impact = 0, contact_steps = 0, smooth_deficit = 0;
    double work = 0, corr = 0, points = 0;  // _Loop: work, corr, points
    double act = 0, obs = 0;  // Recorder._act, ._obs
    double rest = 0;  // Recorder._rest: the log ends with a stretch of persistent steps of these many rows
    // Invariants: E0, E, Ehat, Emin, scale, booked, external, residual, Es, v_app, deep_points, deep_samples,
    // last_depth, last_allowed, points
    double i_E0 = 0, i_E = 0, i_Ehat = 0, i_Emin = 0, i_scale = 0, i_booked = 0, i_external = 0, i_residual = 0;
    double i_Es = 0, i_v_app = 0, i_deep_points = 0, i_deep_samples = 0, i_last_depth = 0, i_last_allowed = 0;
    double i_points = 0;
    // WORSEN times the size each invariant was last reported at (Invariants._violate reports nothing below it)
    double w_gain = 0, w_speed = 0, w_depth = 0, w_ledger = 0;
    std::vector<std::array<int64_t, 3>> previous;  // _Loop.previous: (pair, kind, feature) of the last step
    std::vector<std::pair<int64_t, double>> held;  // Invariants.held: pair -> allowance [m]

#define MOREAU_CARRY(X)                                                                                           \
  X(smooth) X(diss) X(law) X(E) X(T) X(V) X(rise) X(t_rise) X(law_diff) X(t_law_diff) X(new_impact)                \
  X(contact_steps) X(smooth_deficit) X(work) X(corr) X(points) X(i_E0) X(i_E) X(i_Ehat) X(i_Emin) X(i_scale)      \
  X(i_booked) X(i_external) X(i_residual) X(i_Es) X(i_v_app) X(i_deep_points) X(i_deep_samples) X(i_last_depth)  \
  X(i_last_allowed) X(i_points) X(w_gain) X(w_speed) X(w_depth) X(w_ledger) X(act) X(obs) X(rest)
    std::map<std::string, double> as_dict() const {
      std::map<std::string, double> d;
#define MOREAU_PUT(f) d[#f] = f;
      MOREAU_CARRY(MOREAU_PUT)
#undef MOREAU_PUT
      return d;
    }
    void from(const std::map<std::string, double> &d) {
#define MOREAU_GET(f)                                                                         \
  {                                                                                           \
    auto it = d.find(#f);                                                                     \
    if (it == d.end()) throw nb::value_error("carry: " #f " missing");                        \
    f = it->second;                                                                           \
  }
      MOREAU_CARRY(MOREAU_GET)
#undef MOREAU_GET
    }
#undef MOREAU_CARRY
  };

  nb::object py_stepper_;
  Stepper &S_;
  ForestFigures forest_;  // what a sample records (ForestFigures above)
  bool checks_;
  bool guard_ = false;  // Undo restores the box pairs' detection state (a model with pairs of two boxes)
  // coal's cached GJK guesses of the pairs' distance queries (requests, results) before the current step (Undo)
  QueryGuesses dist_;
  double log_relative_, acceleration_, gap_round_off_, rel_, rel_ledger_, tol_, g_, rest_accuracy_;
  int64_t persist_;
  Carry c_;
  double t_ = 0;
  VectorXd q_, u_;
  int64_t k_ = 0;
  std::array<int64_t, 3> written_{0, 0, 0};
  int64_t log_room_ = 0, log_need_ = 1;  // the log's rows free for the next step; the most one step has needed
  bool full_ = false;  // step() returned false for want of log rows (advance: Stop::FULL, not a hand-back)
  int64_t flight_ = 0, contact_ = 0;
  std::vector<Eigen::Index> logged_;  // step(): the contacts of the step's log rows (kept: no allocation a step)
  std::optional<actuation::Actuation> act_;  // the joint torques (none: a passive run)
  Col<double> s_act, s_obs;  // the EXTERNAL columns (trajectory.EXTERNAL) of a run with work done on it (§5.5)
  bool external_ = false;  // the samples have them (torques, moving statics, drives: Recorder._external)
  // the columns (trajectory.SAMPLES, LOG, IMPACTS)
  Col<double> s_t, s_q, s_u, s_T, s_V, s_work, s_corr, s_gap, s_smooth, s_diss, s_law;
  Col<int64_t> s_n;
  Col<int64_t> l_step, l_pair, l_kind, l_feature, l_steps;
  Col<double> l_t, l_gap, l_P, l_gm, l_gp, l_point, l_normal, l_duration;
  Col<bool> l_impact;
  Col<int64_t> i_step, i_contacts;
  Col<double> i_t, i_Tm, i_Tp, i_diss, i_law;

  void bind(const nb::dict &s, const nb::dict &l, const nb::dict &i) {
    s_t = run_loop::column<double>(s, "t"), s_q = run_loop::column<double>(s, "q"), s_u = run_loop::column<double>(s, "u");
    s_T = run_loop::column<double>(s, "kinetic_energy"), s_V = run_loop::column<double>(s, "potential_energy");
    s_work = run_loop::column<double>(s, "contact_work"), s_corr = run_loop::column<double>(s, "correction_energy");
    s_gap = run_loop::column<double>(s, "gap"), s_n = run_loop::column<int64_t>(s, "n_contacts");
    s_smooth = run_loop::column<double>(s, "smooth_error"), s_diss = run_loop::column<double>(s, "dissipation");
    s_law = run_loop::column<double>(s, "law_dissipation");
    external_ = s.contains("actuator_work");
    if (external_) s_act = run_loop::column<double>(s, "actuator_work"), s_obs = run_loop::column<double>(s, "obstacle_work");
    l_step = run_loop::column<int64_t>(l, "log_step"), l_t = run_loop::column<double>(l, "log_t"), l_pair = run_loop::column<int64_t>(l, "log_pair");
    l_kind = run_loop::column<int64_t>(l, "log_kind"), l_feature = run_loop::column<int64_t>(l, "log_feature");
    l_gap = run_loop::column<double>(l, "log_gap"), l_P = run_loop::column<double>(l, "log_P");
    l_gm = run_loop::column<double>(l, "log_gamma_minus"), l_gp = run_loop::column<double>(l, "log_gamma_plus");
    l_point = run_loop::column<double>(l, "log_point"), l_normal = run_loop::column<double>(l, "log_normal");
    l_impact = run_loop::column<bool>(l, "log_impact"), l_steps = run_loop::column<int64_t>(l, "log_steps");
    l_duration = run_loop::column<double>(l, "log_duration");
    i_step = run_loop::column<int64_t>(i, "impact_step"), i_t = run_loop::column<double>(i, "impact_t");
    i_contacts = run_loop::column<int64_t>(i, "impact_contacts"), i_Tm = run_loop::column<double>(i, "impact_T_minus");
    i_Tp = run_loop::column<double>(i, "impact_T_plus"), i_diss = run_loop::column<double>(i, "impact_dissipation");
    i_law = run_loop::column<double>(i, "impact_law");
  }

  // ---- the forest's figures, as trees.Forest and contacts.pair_distances compute them (src/forest.hpp) -----------
  double kinetic(const VectorXd &q, const VectorXd &u) { return forest_.kinetic(q, u); }
  double potential(const VectorXd &q) { return forest_.potential(q); }
  void gaps(const VectorXd &q, double *out) { forest_.gaps(q, out); }

  static double pymax(double a, double b) { return b > a ? b : a; }  // Python's max(a, b)

  // ---- undoing a step the Stepper took (a check that fires, a non-finite figure): the detection state it moved ----
  // A model with pairs of two boxes carries, from one detection to the next, coal's cached GJK guesses and the
  // pairs with contacts (contacts.detect's warm start; data.Data.warm_start lists them): the Python step that retakes
  // an undone step must find them as they were before it. The collision queries' guesses are the ones the Stepper
  // saved at the step's detection (its first act: Stepper::save_guesses, restored as on its own fallback), the warm
  // start is the buffer it swapped at the step's end (swapped back); only the distance queries' guesses (the step's
  // position-correction guard, the sample's gaps) are copied here, before each step.
  void save_distances() { dist_.save(S_.gd_.distanceRequests, S_.gd_.distanceResults); }
  // restores, unless committed, what the step (returned by the Stepper, not handed back by it) moved
  struct Undo {
    Runner &R;
    bool committed = false;
    ~Undo() {
      Stepper &S = R.S_;
      if (committed) {
        S.journal_end();
        return;
      }
      S.active_.swap(S.next_active_);  // the projection's warm start, as before the step (Stepper::step swapped it)
      if (!R.guard_) return;
      S.restore_guesses();
      S.warm_.swap(S.next_warm_);
      R.dist_.restore(S.gd_.distanceRequests, S.gd_.distanceResults);
      S.journal_restore(), S.journal_end();  // a scene without a pair list: Python's distance queries (Stepper::table)
    }
  };

  // ledger.at_rest: |gamma_i^k|, |gamma_i^{k+1}| <= REST_ACCURACY rho_i, rho = |W|' (|u_k| + |u_free - u_k|) (odot)
  // (over the rows of W the step wrote, StepOut::wptr, where x is finite: the other terms add +-0, contact_space's
  // argument)
  bool at_rest(const StepOut &r, const VectorXd &u) const {
    const VectorXd x = u.cwiseAbs() + (r.u_free - u).cwiseAbs();
    const Eigen::Index nv = r.W.rows();
    const bool listed = r.wptr.size() == (size_t)r.m + 1 && x.allFinite();
    VectorXd w(nv);
    for (Eigen::Index i = 0; i < r.m; ++i) {
      double sum = 0.0;
      if (listed) {
        const Eigen::Index a = r.wptr[(size_t)i], b = r.wptr[(size_t)i + 1];
        for (Eigen::Index t = a; t < b; ++t) {
          const Eigen::Index v = r.wrow[(size_t)t];
          const double term = std::abs(r.W(v, i)) * x[v];
          sum = t == a ? term : sum + term;
        }
        sum = sum + 0.0;
      } else if (nv) {
        w = r.W.col(i).cwiseAbs();
        sum = odot(w.data(), x.data(), nv);
      }
      const double bound = rest_accuracy_ * sum;
      if (!(std::abs(r.gamma_minus[i]) <= bound && std::abs(r.gamma_plus[i]) <= bound)) return false;
    }
    return true;
  }

  // ledger.law_kept: u_{k+1} is law.outcome(v, u_k, e) bit for bit (no energy cap, no lift paid with the velocities)
  static bool law_kept(const StepOut &r, const VectorXd &u, double e) {
    const VectorXd law = r.v - e * (u - r.v);
    return law.size() == r.u_next.size() &&
           !std::memcmp(law.data(), r.u_next.data(), sizeof(double) * (size_t)law.size());
  }

  // one step k -> k + 1; false: handed back, nothing committed
  bool step(int64_t k, int64_t n, int64_t every, double h, double e, double t0, const std::array<int64_t, 3> &starts) {
    VectorXd tau;  // stepper.torque: at (t_m, q_m, u_k), once a step (empty: none)
    if (act_ && !act_->torque(t_ + 0.5 * h, pinocchio::integrate(S_.model_, q_, (0.5 * h) * u_), u_, tau))
      return false;  // the controller failed: compiled_run.py raises its error (nothing committed)
    if (guard_) {
      save_distances();
      if (S_.table_) S_.journal_begin();  // Python's distance queries: their guesses as they go (Undo)
    }
    StepOut r = S_.step(q_, u_, h, e, tau, t_);
    if (r.outcome == Outcome::FALLBACK) {  // the Stepper restored what it moved, but its guard's distance queries
      S_.journal_restore(), S_.journal_end();
      return false;
    }
    Undo undo{*this};  // every return below but the commit undoes the step
    if (!(r.q_next.allFinite() && r.u_next.allFinite())) return false;  // TimeStepping.step: FAILED
    Carry c = c_;
    const double t1 = t0 + (double)(k + 1) * h;
    const double tm = t_ + 0.5 * h;
    const Eigen::Index m = r.outcome == Outcome::CONTACT ? r.m : 0;
    const int64_t index = k + 1;  // TimeStepping's FixedStep.index: the log's and the impact rows' step
    // _Loop.account: rep.work, rep.corr
    c.work += r.contact_work;
    c.corr += r.correction_energy;
    // Recorder.log_percussions and ._log_step: this step's rows, or P added to the stretch of persistent steps the
    // log ends with (at the commit: a step undone leaves those rows as they were)
    int64_t nlog = 0;
    c.new_impact = 0.0;
    bool persistent = false;  // a persistent contact step (ledger.at_rest, docs/theory.md §5.2): no impact to book
    std::vector<Eigen::Index> &logged = logged_;  // the contacts of this step's rows
    logged.clear();
    bool fold = false;
    if (m) {
      double pmax = r.P[0];
      for (Eigen::Index i = 1; i < m; ++i) pmax = pymax(pmax, r.P[i]);  // numpy max (no NaN here: finite state)
      const double cut = pymax(log_relative_ * pmax, 0.0);
      std::vector<std::array<int64_t, 3>> keys(m);
      for (Eigen::Index i = 0; i < m; ++i) keys[i] = {r.pair[i], r.kind[i], r.feature[i]};
      bool held = true;  // Recorder._held: every contact closed in the step before
      for (Eigen::Index i = 0; i < m && held; ++i)
        held = std::binary_search(c.previous.begin(), c.previous.end(), keys[i]);
      persistent = held && at_rest(r, u_) && law_kept(r, u_, e);
      for (Eigen::Index i = 0; i < m; ++i) {
        if (!(r.P[i] > cut)) continue;
        logged.push_back(i);
        if (!std::binary_search(c.previous.begin(), c.previous.end(), keys[i])) c.new_impact = 1.0;
      }
      const int64_t k = (int64_t)logged.size(), end = starts[1] + written_[1];  // end: the log's next row
      fold = persistent && k && (int64_t)c.rest == k;
      for (int64_t j = 0; j < k && fold; ++j) {
        const int64_t row = end - k + j;
        const auto &key = keys[logged[j]];
        fold = *l_pair.at(row) == key[0] && *l_kind.at(row) == key[1] && *l_feature.at(row) == key[2];
      }
      if (!fold) {
        if (k > log_room_) {  // no room for its rows: undone, and the next call reserves them (compiled_run.py)
          log_need_ = k, full_ = true;
          return false;
        }
        log_need_ = std::max(log_need_, k);
        for (const Eigen::Index i : logged) {
          const bool fresh = !std::binary_search(c.previous.begin(), c.previous.end(), keys[i]);
          const int64_t row = end + nlog++;
          *l_step.at(row) = index, *l_t.at(row) = tm, *l_pair.at(row) = keys[i][0], *l_kind.at(row) = keys[i][1];
          *l_feature.at(row) = keys[i][2], *l_gap.at(row) = r.g[i], *l_P.at(row) = r.P[i];
          *l_gm.at(row) = r.gamma_minus[i], *l_gp.at(row) = r.gamma_plus[i];
          for (int j = 0; j < 3; ++j) l_point.at(row)[j] = r.point_a(i, j), l_normal.at(row)[j] = r.normal(i, j);
          *l_impact.at(row) = fresh, *l_steps.at(row) = 1, *l_duration.at(row) = h;
        }
      }
      c.rest = persistent ? (double)k : 0.0;
      std::sort(keys.begin(), keys.end());
      keys.erase(std::unique(keys.begin(), keys.end()), keys.end());
      c.previous = std::move(keys);
    } else {
      c.previous.clear();
      c.rest = 0.0;
    }
    // Recorder.account_step (the state it starts from is the one the ledger accounted last: compiled_run.py)
    const double E0 = c.E;
    const double T1 = kinetic(r.q_next, r.u_next), V1 = potential(r.q_next);
    if (!(std::isfinite(T1) && std::isfinite(V1))) return false;  // an overflow: the Python run names it
    const double E1 = T1 + V1;
    const double obstacle = r.obstacle_work;  // the work of prescribed motion (§5.5)
    c.obs += obstacle;
    // the torques' work h tau.(u_k + u_{k+1})/2 (sums.ordered: odot)
    const double act = tau.size() ? (0.5 * h) * odot(tau.data(), VectorXd(u_ + r.u_next).data(), tau.size()) : 0.0;
    c.act += act;
    const double rise = E1 - E0 - pymax(r.correction_energy, 0.0) - act - obstacle;
    if (rise > c.rise) c.rise = rise, c.t_rise = t1;
    int64_t nimp = 0;
    if (!m) {
      c.smooth += E1 - E0 - act - obstacle;
    } else {  // ledger.impact_terms(M, v_free, v, u_k, u_{k+1}, e, P, b), the smooth step at q_free
      double law = 0.0, T_minus = 0.0, T_plus = 0.0;
      if (!persistent) {
        VectorXd tmp;
        // u_{k+1} as the law left it: before a lift the correction paid with the velocities (§2.5; Recorder's u_law)
        const VectorXd u_plus = (r.paid ? r.u_law : r.u_next) - e * (r.v_free - u_);
        const VectorXd res = r.v_free - r.v;
        law = 0.5 * (1.0 - e * e) * r.quad_M(res, tmp);
        law -= odot(r.P.data(), r.b.data(), m);  // b: the restitution bounds (zeros without; P.0 = +0.0)
        T_minus = 0.5 * r.quad_M(r.v_free, tmp), T_plus = 0.5 * r.quad_M(u_plus, tmp);
      }
      const VectorXd q_half = pinocchio::integrate(S_.model_, q_, (0.5 * h) * u_);
      const VectorXd q_free = pinocchio::integrate(S_.model_, q_half, (0.5 * h) * r.u_free);
      const double act_free =
          tau.size() ? (0.5 * h) * odot(tau.data(), VectorXd(u_ + r.u_free).data(), tau.size()) : 0.0;
      const double drive_free = r.drive_work_free;
      // contacts that left the smooth motion as it was, bit for bit (u_{k+1} = u_free, q_{k+1} = q_free): its
      // energy is E1's (Recorder.account_step)
      const bool same = r.u_free.size() == r.u_next.size() && q_free.size() == r.q_next.size() &&
                        !std::memcmp(r.u_free.data(), r.u_next.data(), sizeof(double) * (size_t)r.u_free.size()) &&
                        !std::memcmp(q_free.data(), r.q_next.data(), sizeof(double) * (size_t)q_free.size());
      const double S = (same ? E1 : kinetic(q_free, r.u_free) + potential(q_free)) - E0 - act_free - drive_free;
      c.smooth += S;
      if (S < 0.0) c.smooth_deficit -= S;
      // Recorder._add_impact (given = the obstacle work); a persistent step only counts
      c.contact_steps += 1;
      if (!persistent) {
        int64_t pushing = 0;
        for (Eigen::Index i = 0; i < m; ++i) pushing += r.P[i] > 0.0;
        double dissipated = T_minus - T_plus;
        if (!(obstacle == 0.0)) dissipated = dissipated + obstacle, law = law + obstacle;  // `if given:`
        c.diss += dissipated;
        c.law += law;
        const double diff = std::abs(dissipated - law);
        if (diff > c.law_diff) c.law_diff = diff, c.t_law_diff = tm;
        if (c.new_impact != 0.0) {
          const int64_t row = starts[2] + written_[2];
          *i_step.at(row) = index, *i_t.at(row) = tm, *i_contacts.at(row) = pushing;
          *i_Tm.at(row) = T_minus, *i_Tp.at(row) = T_plus, *i_diss.at(row) = dissipated, *i_law.at(row) = law;
          nimp = 1;
        }
      }
    }
    c.E = E1, c.T = T1, c.V = V1;
    // the sample (_Loop._sample, Recorder.sample) and its check
    const bool due = (k + 1) % every == 0 || k == n - 1;
    bool fire = false;
    int64_t nsamp = 0;
    if (due) {
      const int64_t row = starts[0] + written_[0];
      double *gap = s_gap.at(row);
      if (!S_.rh_.moving.empty())  // Recorder.sample: the gaps at the sample's time
        S_.rh_.place(const_cast<pinocchio::GeometryModel &>(S_.gm_), t1);
      gaps(r.q_next, gap);
      const bool far = forest_.per_geometry();  // +inf: no partner within reach (Recorder.finite), not an overflow
      for (int64_t j = 0; j < s_gap.row; ++j)
        if (!std::isfinite(gap[j]) && !(far && gap[j] == INFINITY))
          return false;  // coal failed, or an overflow: the Python run names it
      *s_t.at(row) = t1;
      std::copy(r.q_next.data(), r.q_next.data() + r.q_next.size(), s_q.at(row));
      std::copy(r.u_next.data(), r.u_next.data() + r.u_next.size(), s_u.at(row));
      *s_T.at(row) = T1, *s_V.at(row) = V1, *s_work.at(row) = c.work, *s_corr.at(row) = c.corr;
      *s_n.at(row) = (int64_t)m;
      const double E = T1 + V1;  // Recorder._smooth_until
      c.smooth += E - c.E;
      if (E - c.E > c.rise) c.rise = E - c.E, c.t_rise = t1;
      *s_smooth.at(row) = c.smooth, *s_diss.at(row) = c.diss, *s_law.at(row) = c.law;
      double external = 0.0;  // Recorder.last_sample's actuator + obstacle work
      if (external_) *s_act.at(row) = c.act, *s_obs.at(row) = c.obs, external = c.act + c.obs;
      const double work = c.work, corr = c.corr, smooth = c.smooth;
      c.smooth = c.diss = c.law = c.act = c.obs = 0.0;
      c.E = E;
      c.work = c.corr = 0.0;
      nsamp = 1;
      if (checks_) {  // Invariants._sample
        const double Es = c.i_Es;
        c.i_Es = T1 + V1;
        if (Es == Es) {
          const double residual = c.i_residual = c.i_residual + ((T1 + V1) - Es - (work + corr + smooth + external));
          const double bound = rel_ledger_ * c.i_scale;
          if (residual - c.smooth_deficit > bound && std::abs(residual) > c.w_ledger) fire = true;
          if (s_gap.row) {
            double gmin = gap[0];
            for (int64_t j = 1; j < s_gap.row; ++j) gmin = std::min(gmin, gap[j]);
            const double depth = -gmin;
            const double allowed = tol_ + h * c.i_v_app + gap_round_off_;
            if (depth > allowed) {
              c.i_deep_samples += 1;
              c.i_last_depth = depth, c.i_last_allowed = allowed;
              if (c.i_deep_samples >= persist_ && depth > c.w_depth) fire = true;
            } else if (c.i_deep_samples != 0.0) {
              c.i_deep_samples = 0;
            }
          }
        }
      }
    }
    if (checks_) {  // Invariants._point
      c.i_points += 1;
      const double T = T1, V = V1, E = T + V;
      const double dE = E - c.i_E;
      double booked = r.correction_energy;
      double ext = 0.0;
      if (tau.size()) ext += act;
      ext += obstacle;
      double deep = 0.0, allowed = 0.0;
      if (m) {
        const double grow = acceleration_ * h * g_;
        std::vector<std::pair<int64_t, double>> held;
        auto find = [](const std::vector<std::pair<int64_t, double>> &v, int64_t p, double dflt) {
          for (auto &x : v)
            if (x.first == p) return x.second;
          return dflt;
        };
        for (Eigen::Index i = 0; i < m; ++i) {
          const double gi = r.g[i], vi = r.gamma_minus[i];
          const int64_t p = r.pair[i];
          if (-vi > c.i_v_app) c.i_v_app = -vi;
          if (-gi > tol_) {
            double a = tol_ + h * (pymax(-vi, 0.0) + grow) + gap_round_off_;
            a = pymax(pymax(a, find(c.held, p, 0.0)), find(held, p, 0.0));
            bool set = false;
            for (auto &x : held)
              if (x.first == p) x.second = a, set = true;
            if (!set) held.push_back({p, a});
            if (-gi - a > deep - allowed) deep = -gi, allowed = a;
          }
        }
        c.held = std::move(held);
      } else {
        c.held.clear();
        booked = dE - ext;
      }
      c.i_E = E;
      if (booked > 0.0) c.i_booked += booked;
      c.i_external += ext;
      const double Ehat = c.i_Ehat = c.i_Ehat + (dE - booked - ext);
      if (T > c.i_scale) c.i_scale = T;
      const double bound = rel_ * c.i_scale;
      if (Ehat < c.i_Emin)
        c.i_Emin = Ehat;
      else if (Ehat - c.i_Emin > bound && Ehat - c.i_Emin > c.w_gain)
        fire = true;
      const double budget = c.i_E0 - V + c.i_booked + c.i_external + bound;
      if (T > budget && T - budget > c.w_speed) fire = true;
      if (deep > allowed) {
        c.i_deep_points += 1;
        c.i_last_depth = deep, c.i_last_allowed = allowed;
        if (c.i_deep_points >= persist_ && deep > c.w_depth) fire = true;
      } else if (c.i_deep_points != 0.0) {
        c.i_deep_points = 0;
      }
    }
    if (fire) return false;  // a violation to report: the Python run takes this step and reports it
    c.points += 1;
    // commit
    undo.committed = true;
    if (fold) {
      const int64_t k = (int64_t)logged.size(), end = starts[1] + written_[1];
      for (int64_t j = k; j > 0; --j) {
        const int64_t row = end - j;
        *l_P.at(row) += r.P[logged[k - j]], *l_steps.at(row) += 1, *l_duration.at(row) += h;
      }
    }
    c_ = std::move(c);
    written_[0] += nsamp, written_[1] += nlog, written_[2] += nimp;
    (m ? contact_ : flight_) += 1;
    t_ = t1, q_ = std::move(r.q_next), u_ = std::move(r.u_next), k_ = k + 1;
    return true;
  }
};

void bind_run(nb::module_ &mod) {
  nb::enum_<Stop>(mod, "Stop", "Why Runner.advance returned (moreau_sim/compiled_run.py)")
      .value("FINISHED", Stop::FINISHED)
      .value("POLL", Stop::POLL)
      .value("CHECKPOINT", Stop::CHECKPOINT)
      .value("FULL", Stop::FULL)
      .value("HAND_BACK", Stop::HAND_BACK);
  nb::class_<Runner>(mod, "Runner", "The time-stepping run loop over a Stepper (src/run.cpp)")
      .def(nb::init<nb::object, std::vector<std::tuple<nb::object, nb::object, int64_t, int64_t, int64_t, int64_t>>,
                    std::vector<int64_t>, std::vector<int64_t>,
                    const std::map<std::string, double> &, bool, nb::object>(),
           nb::arg("stepper"), nb::arg("trees"), nb::arg("tree_of_joint"), nb::arg("local_joint"),
           nb::arg("constants"), nb::arg("checks"), nb::arg("torques").none())
      .def("advance", &Runner::advance)
      .def("carry", &Runner::carry)
      .def("load", &Runner::load)
      .def("previous", &Runner::previous)
      .def("log_need", &Runner::log_need)
      .def("held", &Runner::held)
      .def("where", &Runner::where)
      .def("written", &Runner::written)
      .def("counts", &Runner::counts);
}
