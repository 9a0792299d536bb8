// moreau_sim._step: the midpoint Moreau contact step of moreau_sim/stepper.py in C++, on the
// pin.Model, the forest's per-tree pin.Models and pin.Datas (src/forest.hpp; no Data of the whole model,
// docs/theory.md §2.12), GeometryModel / GeometryData built in Python (taken by reference through
// boost.python's registry: the same Pinocchio and coal libraries as the Python bindings).
//
// It mirrors stepper.step stage by stage and operation by operation (the same products and sums in
// the same order, no FMA contraction: docs/theory.md §2.8), for the contacts of every pair: coal's closed-form
// pairs (moreau_sim/compiled.py _analytic), its warm-started GJK/EPA on the same
// GeometryData (the guesses saved before the detection, restored where a step is handed back), pairs of two boxes
// (src/box_box.hpp: point queries, contact patches, the warm start of contacts.detect), on the broad phase's
// candidates (broad_phase.py) in a model of more than its MIN_PAIRS pairs, and in a scene without a pair list on
// its pair table (src/pair_table.hpp) through the coal objects the Python step makes per pair; any number of
// velocities: polytope
// vertices against a half-space (contacts._vertex_contacts, kind "plane") or any other shape (coal's point query),
// coal's witness contact (smooth shapes), patches (contacts._face_axis, _snap), flight steps; the
// restitution rules (law.restitution_bounds); the projection (qp.solve's screen, the closed form for one
// contact, else qp._active_set's dual active set from nothing, re-solved and checked as qp._polish does);
// the energy-budgeted position correction with its pair-distance guard and its lift paid with the velocities
// (docs/theory.md §2.5); the rheonomic steps (§2.9, §2.13): moving statics placed at t_m and their contacts' rates,
// driven joints' reduced step (drive_start; the schedules of src/rheonomic.hpp, handed over once by
// Stepper::rheonomic). Anything else returns FALLBACK with a reason and the Python step (the reference) takes the
// step: corners, edge contacts of two boxes, a point query against a box turned in its joint frame, swept
// detection, coal's EPA fallback, a projection of more than qp.WARM_ROWS rows without a start (qp.solve's sparse
// path alone), a projection the active set does not settle (where qp.solve turns to piqp), a driven step whose
// contact only driven rows move.
#include <cstring>
#include <memory>
#include <mutex>
#include <nanobind/nanobind.h>
#include <nanobind/eigen/dense.h>
#include <nanobind/stl/array.h>
#include <nanobind/stl/map.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/tuple.h>
#include <nanobind/stl/vector.h>

#include <boost/python.hpp>
#ifdef __GLIBC__
#include <malloc.h>
#endif

#include <pinocchio/multibody/model.hpp>
#include <pinocchio/multibody/data.hpp>
#include <pinocchio/multibody/geometry.hpp>
#include <pinocchio/algorithm/joint-configuration.hpp>
#include <pinocchio/algorithm/crba.hpp>
#include <pinocchio/algorithm/aba.hpp>
#include <pinocchio/algorithm/energy.hpp>
#include <pinocchio/algorithm/geometry.hpp>
#include <pinocchio/collision/collision.hpp>
#include <pinocchio/collision/distance.hpp>

#include <coal/contact_patch.h>
#include <coal/distance.h>
#include <coal/shape/geometric_shapes.h>

#include "box_box.hpp"
#include "pair_table.hpp"
#include "rheonomic.hpp"

#include <algorithm>
#include <array>
#include <atomic>
#include <cfloat>
#include <cmath>
#include <limits>
#include <map>
#include <optional>
#include <unordered_map>
#include <string>
#include <tuple>
#include <type_traits>
#include <vector>

namespace nb = nanobind;
namespace bp = boost::python;
using Eigen::MatrixXd;
using Eigen::VectorXd;
using Vec3 = Eigen::Vector3d;
using VectorXl = Eigen::Matrix<int64_t, Eigen::Dynamic, 1>;

namespace {

// What a step did (bound as moreau_sim._step.Outcome); how its projection was solved (Projection)
enum class Outcome { FLIGHT, CONTACT, FALLBACK };
enum class Projection { ADMISSIBLE, ACTIVE_SET };

// The constants the step shares with the Python step, each passed from its one home in Python
// (moreau_sim/compiled.py CONSTANTS); none has a value of its own here.
struct Constants {
  int midpoint_iterations;  // stepper.MIDPOINT_ITERATIONS
  double midpoint_tolerance;  // stepper.MIDPOINT_TOLERANCE
  double resting, hold;  // results.RESTING, HOLD
  int vertex, witness, joint_limit;  // contacts.FeatureKind.VERTEX, .WITNESS, .JOINT_LIMIT
  int warm_rows;  // qp.WARM_ROWS: above it a projection without a start hands back (qp.solve's sparse path, §1.3)
  int sparse_rows;  // qp.SPARSE_ROWS: above it the projection starts from the previous step's final set (§1.3)
  double screen, dependent, met, accept, refine, second_pass;  // qp.SCREEN, DEPENDENT, MET, ACCEPT, REFINE, SECOND_PASS
  int moves_per_row, moves_extra, start_passes;  // qp.MOVES_PER_ROW, MOVES_EXTRA, START_PASSES
  double distinct;  // constraints.distinct's relative tolerance
  double guess_min, distance_failed;  // contacts.GUESS_MIN, DISTANCE_FAILED
  double energy_roundoff;  // law.ENERGY_ROUNDOFF
  int patch, edge, face;  // contacts.FeatureKind.PATCH, .EDGE, .FACE
  double same_point, cone, edge_end, parallel, depth_ratio;  // contacts.SAME_POINT; box_box's CONE, EDGE_END,
                                                             // PARALLEL, DEPTH_RATIO
  double snap;  // contacts.SNAP_COS

  static const std::vector<std::string> &keys() {
    static const std::vector<std::string> k = {
        "midpoint_iterations", "midpoint_tolerance", "resting", "hold", "vertex", "witness", "warm_rows", "sparse_rows",
        "screen", "dependent", "met", "accept", "refine", "second_pass", "moves_per_row", "moves_extra", "start_passes", "distinct",
        "guess_min", "distance_failed", "joint_limit",
        "energy_roundoff", "patch", "same_point", "cone", "edge_end", "parallel", "depth_ratio", "snap", "edge", "face"};
    return k;
  }
  // from a dict holding exactly keys() (a missing or an unknown name is an error: nothing is left to a default)
  static Constants from(const std::map<std::string, double> &d) {
    for (const auto &kv : d)
      if (std::find(keys().begin(), keys().end(), kv.first) == keys().end())
        throw nb::value_error(("unknown constant " + kv.first).c_str());
    auto get = [&](const char *k) {
      auto it = d.find(k);
      if (it == d.end()) throw nb::value_error((std::string("constant missing: ") + k).c_str());
      return it->second;
    };
    auto geti = [&](const char *k) {
      const double v = get(k);
      if (v != std::floor(v)) throw nb::value_error((std::string("constant not an integer: ") + k).c_str());
      return (int)v;
    };
    Constants c;
    c.midpoint_iterations = geti("midpoint_iterations"), c.midpoint_tolerance = get("midpoint_tolerance");
    c.resting = get("resting"), c.hold = get("hold"), c.vertex = geti("vertex"), c.witness = geti("witness");
    c.warm_rows = geti("warm_rows"), c.sparse_rows = geti("sparse_rows"), c.screen = get("screen"), c.dependent = get("dependent");
    c.met = get("met"), c.accept = get("accept"), c.refine = get("refine"), c.second_pass = get("second_pass");
    c.moves_per_row = geti("moves_per_row"), c.moves_extra = geti("moves_extra"), c.distinct = get("distinct");
    c.start_passes = geti("start_passes");
    c.guess_min = get("guess_min"), c.distance_failed = get("distance_failed");
    c.joint_limit = geti("joint_limit");
    c.energy_roundoff = get("energy_roundoff");
    c.patch = geti("patch"), c.same_point = get("same_point"), c.cone = get("cone"), c.edge_end = get("edge_end");
    c.parallel = get("parallel"), c.depth_ratio = get("depth_ratio"), c.snap = get("snap");
    c.edge = geti("edge"), c.face = geti("face");
    return c;
  }
  std::map<std::string, double> as_dict() const {
    return {{"midpoint_iterations", midpoint_iterations}, {"midpoint_tolerance", midpoint_tolerance},
            {"resting", resting}, {"hold", hold}, {"vertex", vertex}, {"witness", witness},
            {"warm_rows", warm_rows}, {"sparse_rows", sparse_rows},
            {"screen", screen}, {"dependent", dependent}, {"met", met}, {"accept", accept}, {"refine", refine},
            {"second_pass", second_pass}, {"moves_per_row", moves_per_row}, {"moves_extra", moves_extra}, {"start_passes", start_passes},
            {"distinct", distinct}, {"guess_min", guess_min}, {"distance_failed", distance_failed},
            {"joint_limit", joint_limit},
            {"energy_roundoff", energy_roundoff}, {"patch", patch}, {"same_point", same_point}, {"cone", cone},
            {"edge_end", edge_end}, {"parallel", parallel}, {"depth_ratio", depth_ratio}, {"snap", snap},
            {"edge", edge}, {"face", face}};
  }
};

template <class T> T &extract_ref(nb::handle h, const char *what) {
  bp::object o{bp::handle<>(bp::borrowed(h.ptr()))};
  bp::extract<T &> x(o);
  if (!x.check()) throw nb::type_error((std::string("expected a ") + what).c_str());
  return x();
}

// coal warm-starts GJK's support search from the previous call of the same pair (a hint kept in the
// collision functor's solver, a protected member): a step handed to Python must find the hints as the
// Python step would have left them, so they are saved before detection and restored on a fallback.
struct SolverOf : coal::ComputeCollision {
  static coal::GJKSolver coal::ComputeCollision::*member() { return &SolverOf::solver; }
};
struct DistanceSolverOf : coal::ComputeDistance {  // the same hints of a distance functor
  static coal::GJKSolver coal::ComputeDistance::*member() { return &DistanceSolverOf::solver; }
};

// data.Data.reset: every cached GJK guess and support hint a run leaves in these coal objects back to a new object's
// (the GeometryData's requests, results and functors; requests and results of Python's), the same in every process
void reset_guesses(nb::object geom_data, const std::vector<nb::object> &requests, const std::vector<nb::object> &results) {
  static const coal::CollisionRequest rq0;
  static const coal::CollisionResult rs0;
  static const coal::GJKSolver sv0;
  auto request = [](coal::QueryRequest &r) {
    r.cached_gjk_guess = rq0.cached_gjk_guess, r.cached_support_func_guess = rq0.cached_support_func_guess;
  };
  auto result = [](coal::QueryResult &r) {
    r.cached_gjk_guess = rs0.cached_gjk_guess, r.cached_support_func_guess = rs0.cached_support_func_guess;
  };
  auto solver = [](coal::GJKSolver &sv) {
    sv.cached_guess = sv0.cached_guess, sv.support_func_cached_guess = sv0.support_func_cached_guess;
  };
  if (!geom_data.is_none()) {
    auto &gd = extract_ref<pinocchio::GeometryData>(geom_data, "pinocchio.GeometryData");
    for (auto &r : gd.collisionRequests) request(r);
    for (auto &r : gd.distanceRequests) request(r);
    for (auto &r : gd.collisionResults) result(r);
    for (auto &r : gd.distanceResults) result(r);
    for (auto &f : gd.collision_functors) solver(f.*SolverOf::member());
    for (auto &f : gd.distance_functors) solver(f.*DistanceSolverOf::member());
  }
  for (const nb::object &o : requests) request(extract_ref<coal::QueryRequest>(o, "coal request"));
  for (const nb::object &o : results) result(extract_ref<coal::QueryResult>(o, "coal result"));
}

struct Found {
  double g;
  Vec3 pa, pb, n;
  int pair, kind, feature;
};

struct Fallback {
  std::string why;
};

// np.minimum's min of two doubles: NaN where either is (the correction's guard, np.minimum.at)
inline double nan_min(double a, double b) {
  return (std::isnan(a) || std::isnan(b)) ? std::numeric_limits<double>::quiet_NaN() : std::min(a, b);
}

struct Solved {  // a projection: v, lam, how it was solved; act: the active set's first pass's final set (qp._polish)
  VectorXd v, lam;
  Projection status;
  std::vector<char> act = {};
};

// One step as it crosses to Python (bound as moreau_sim._step.StepOut; moreau_sim/compiled.py makes it a
// results.StepResult). Its outcome, reason (FALLBACK), m, the projection's status and two scalars are
// attributes; its arrays, named below, cross in two buffers (floats, ints: two numpy arrays per step, each
// made costs ~1 us) laid out by visit(), the one definition of the layout, which layout() gives Python; M and W
// (O(nv^2), O(nv m)) cross as views of their own (buffers 2 and 3, made only where Python reads them), not copied
// into floats. The two buffers are filled when Python first reads them (pack): a step the compiled run loop
// takes (src/run.cpp) never fills them.
// FLIGHT: q_next, u_next (= u_free); CONTACT: all (u_law only where paid).
using RowMatrixXd = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
// the diagonal blocks of a block-diagonal (nv, nv) matrix, (first index, size) each, in order, covering 0..nv: the
// kinematic trees' M and M^-1 (docs/theory.md §2.12)
using Blocks = std::vector<std::pair<Eigen::Index, Eigen::Index>>;
// A StepOut's M and W handed back where Python drops the step (~StepOut), taken by a later step of the same sizes
// (no fresh O(nv^2) allocation, no page faults, per step): at most two of each kept. Every entry of a matrix taken
// is written before it is read (contact_rows, M's assignment).
struct Spare {
  std::mutex mu;
  std::vector<MatrixXd> W;
  std::vector<RowMatrixXd> M;
  // a stored matrix of r*c entries, else a new one; `zeroed`: the new one +0.0 everywhere, as the W store's are
  // (~StepOut and the step clear what they wrote). A zeroed column-major one of another number of columns is a
  // stored one of r rows resized in place (realloc: the pages it had are kept; only the columns it grows by are
  // new, cleared): W's columns change with the contacts at every step, and a fresh (nv, m) matrix had the kernel
  // clear every page of it (a third of a step in the 1000-cube pile)
  template <class Mat>
  static Mat take(std::mutex &mu, std::vector<Mat> &v, Eigen::Index r, Eigen::Index c, bool zeroed = false) {
    {
      std::lock_guard<std::mutex> lock(mu);
      for (size_t k = 0; k < v.size(); ++k)
        if (v[k].size() == r * c) {
          Mat x = std::move(v[k]);
          v.erase(v.begin() + (std::ptrdiff_t)k);
          x.resize(r, c);  // the same number of entries: no reallocation
          return x;
        }
      if (zeroed && !Mat::IsRowMajor && c > 0)
        for (size_t k = 0; k < v.size(); ++k)
          if (v[k].rows() == r && v[k].cols() > 0) {
            Mat x = std::move(v[k]);
            v.erase(v.begin() + (std::ptrdiff_t)k);
            const Eigen::Index c0 = x.cols();
            x.conservativeResize(r, c);  // the first min(c0, c) columns kept (+0.0)
            if (c > c0) x.rightCols(c - c0).setZero();
            return x;
          }
    }
    return zeroed ? Mat(Mat::Zero(r, c)) : Mat(r, c);
  }
  // W's entries at the rows `rows` lists for each column (ptr) set to +0.0: all of W's that may be other than +0.0
  static void clear(MatrixXd &W, const std::vector<Eigen::Index> &ptr, const std::vector<Eigen::Index> &rows) {
    for (Eigen::Index j = 0; j + 1 < (Eigen::Index)ptr.size(); ++j)
      for (Eigen::Index t = ptr[(size_t)j]; t < ptr[(size_t)j + 1]; ++t) W(rows[(size_t)t], j) = 0.0;
  }
  template <class Mat> static void give(std::mutex &mu, std::vector<Mat> &v, Mat &x) {
    if (!x.size()) return;
    std::lock_guard<std::mutex> lock(mu);
    if (v.size() < 2) v.push_back(std::move(x));
  }
};
struct StepOut {
  StepOut() = default;
  StepOut(StepOut &&) = default;
  StepOut &operator=(StepOut &&) = default;
  ~StepOut() {
    if (!spare) return;
    Spare::give(spare->mu, spare->M, M);
    if (!W.size()) return;
    if (wptr.size() == (size_t)W.cols() + 1)  // the W store's matrices are +0.0 everywhere (Spare::take, zeroed)
      Spare::clear(W, wptr, wrow);
    else
      W.setZero();
    Spare::give(spare->mu, spare->W, W);
  }
  // M is block diagonal over the kinematic trees (docs/theory.md §2.12): the step keeps its blocks (set_M, O(sum of
  // the trees' nv^2)), the dense (nv, nv) M is made at Python's first read (dense_M), and the run loop's quadratic
  // forms run over the blocks (quad_M)
  void set_M(const MatrixXd &A, const Blocks &blocks) {
    nM = A.rows(), mblocks = blocks;
    Eigen::Index n = 0;
    for (const auto &b : blocks) n += b.second * b.second;
    mval.resize(n);
    n = 0;
    for (const auto &b : blocks)
      for (Eigen::Index k = 0; k < b.second; ++k)
        for (Eigen::Index i = 0; i < b.second; ++i) mval[n++] = A(b.first + i, b.first + k);
  }
  RowMatrixXd &dense_M() {
    if (M.rows() == nM) return M;
    if (spare)
      M = Spare::take(spare->mu, spare->M, nM, nM);
    else
      M.resize(nM, nM);
    M.setZero();  // the entries off the trees' blocks are +0.0, as in the Stepper's M
    Eigen::Index n = 0;
    for (const auto &b : mblocks)
      for (Eigen::Index k = 0; k < b.second; ++k)
        for (Eigen::Index i = 0; i < b.second; ++i) M(b.first + i, b.first + k) = mval[n++];
    return M;
  }
  // x'Mx as the dense form sums it (tmp_j = sums.ordered(x, M[:, j]) then sums.ordered(tmp, x): odot) over the
  // blocks' entries only where x is finite (a term with a zero factor adds +-0: contact_space's argument); else on
  // the dense M
  double quad_M(const VectorXd &x, VectorXd &tmp);
  std::shared_ptr<Spare> spare;  // where M and W go back (the Stepper's)
  Outcome outcome = Outcome::FALLBACK;
  std::string reason;
  Eigen::Index m = 0;
  VectorXd q_next, u_next, u_free;
  // CONTACT: the m closed contacts (contacts.Contacts), the impact and the projection (qp.QPResult)
  VectorXd g;
  Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor> point_a, point_b, normal;
  VectorXl pair, kind, feature, joint_a, joint_b;
  VectorXd P, gamma_minus, gamma_plus, v_free, b, v, lam;
  RowMatrixXd M;  // dense_M's (empty until Python reads it)
  Eigen::Index nM = 0;
  Blocks mblocks;  // (first velocity, nv) of each tree
  VectorXd mval;  // the blocks' entries, block after block, each column-major
  MatrixXd W;  // (nv, m), column-major as constraints.contact_rows makes it
  // the rows of each column of W that may be other than +0.0 (wptr: m + 1 entries; else unknown), ascending: the
  // entries ~StepOut clears and the run loop's sums run over
  std::vector<Eigen::Index> wptr, wrow;
  Projection projection = Projection::ADMISSIBLE;
  double contact_work = 0.0, correction_energy = 0.0;
  // the work of prescribed motion (moving statics' -P.dg/dt, a drive's W_p: results.StepResult.obstacle_work) and a
  // drive's work in the contact-free step (drive_work_free) [J] (docs/theory.md §5.5)
  double obstacle_work = 0.0, drive_work_free = 0.0;
  // a lift the position correction paid with the velocities (stepper.correct_positions, docs/theory.md §2.5):
  // u_law, the law's u_{k+1} before it (results.StepResult.u_law, what the ledger measures the law on, §5.2)
  bool paid = false;
  VectorXd u_law;
  VectorXd floats;  // the arrays that cross, laid out by visit() (filled by pack())
  VectorXl ints;
  bool packed = false;

  // every array that crosses, in order: f(name, data, rows, cols, order) (cols 0: a vector; order 'C' or 'F');
  // M and W are not packed: own(name), their own buffer (layout's 2, 3; 0: in floats or ints)
  static int own(const char *name) { return !std::strcmp(name, "M") ? 2 : !std::strcmp(name, "W") ? 3 : 0; }
  template <class F> void visit(F &&f) {
    f("q_next", q_next.data(), q_next.size(), 0, 'C');
    f("u_next", u_next.data(), u_next.size(), 0, 'C');
    if (outcome != Outcome::CONTACT) return;
    const Eigen::Index nv = u_next.size();
    f("u_free", u_free.data(), nv, 0, 'C');
    f("g", g.data(), m, 0, 'C');
    f("point_a", point_a.data(), m, 3, 'C');
    f("point_b", point_b.data(), m, 3, 'C');
    f("normal", normal.data(), m, 3, 'C');
    f("P", P.data(), m, 0, 'C');
    f("gamma_minus", gamma_minus.data(), m, 0, 'C');
    f("gamma_plus", gamma_plus.data(), m, 0, 'C');
    f("v_free", v_free.data(), nv, 0, 'C');
    f("b", b.data(), m, 0, 'C');
    f("v", v.data(), nv, 0, 'C');
    f("lam", lam.data(), m, 0, 'C');
    f("M", M.data(), nv, nv, 'C');
    f("W", W.data(), nv, m, 'F');
    f("pair", pair.data(), m, 0, 'C');
    f("kind", kind.data(), m, 0, 'C');
    f("feature", feature.data(), m, 0, 'C');
    f("joint_a", joint_a.data(), m, 0, 'C');
    f("joint_b", joint_b.data(), m, 0, 'C');
    if (paid) f("u_law", u_law.data(), nv, 0, 'C');
  }
  template <class T> static constexpr bool is_int = std::is_same_v<std::remove_const_t<T>, int64_t>;
  void pack() {
    if (packed) return;
    packed = true;
    Eigen::Index nf = 0, ni = 0;
    visit([&](const char *name, auto *p, Eigen::Index r, Eigen::Index c, char) {
      if (!own(name)) (is_int<std::remove_pointer_t<decltype(p)>> ? ni : nf) += r * (c ? c : 1);
    });
    floats.resize(nf), ints.resize(ni);
    nf = ni = 0;
    visit([&](const char *name, auto *p, Eigen::Index r, Eigen::Index c, char) {
      if (own(name)) return;
      const Eigen::Index n = r * (c ? c : 1);
      if constexpr (is_int<std::remove_pointer_t<decltype(p)>>)
        std::copy(p, p + n, ints.data() + ni), ni += n;
      else
        std::copy(p, p + n, floats.data() + nf), nf += n;
    });
  }
  // (name, buffer: 0 floats, 1 ints, 2 M, 3 W, offset, rows, cols, order) of each array, in order
  std::vector<std::tuple<std::string, int, Eigen::Index, Eigen::Index, Eigen::Index, char>> layout() {
    std::vector<std::tuple<std::string, int, Eigen::Index, Eigen::Index, Eigen::Index, char>> out;
    Eigen::Index nf = 0, ni = 0;
    visit([&](const char *name, auto *p, Eigen::Index r, Eigen::Index c, char order) {
      if (const int b = own(name)) {
        out.emplace_back(name, b, 0, r, c, order);
        return;
      }
      const bool i = is_int<std::remove_pointer_t<decltype(p)>>;
      out.emplace_back(name, i ? 1 : 0, i ? ni : nf, r, c, order);
      (i ? ni : nf) += r * (c ? c : 1);
    });
    return out;
  }
};

}  // namespace

namespace {

// sums.ordered: a sum of products in index order from the first product, one rounding each (no FMA: this
// file is compiled with -ffp-contract=off), then + 0.0 (a -0.0 sum becomes +0.0); n >= 1
inline double odot(const double *a, const double *b, Eigen::Index n, Eigen::Index sa = 1, Eigen::Index sb = 1) {
  double s = a[0] * b[0];
  for (Eigen::Index k = 1; k < n; ++k) s = s + a[k * sa] * b[k * sb];
  return s + 0.0;
}
// sums.ordered(A, X) for matrices A (r, n) and X (n, c) (Eigen, column-major), into Y (r, c): each entry summed
// as odot does, the loops arranged so that the innermost runs over independent entries (vectorizable)
double StepOut::quad_M(const VectorXd &x, VectorXd &tmp) {
  const Eigen::Index n = x.size();
  if (n == 0) return 0.0;
  tmp.resize(n);
  if (!x.allFinite()) {
    const RowMatrixXd &A = dense_M();
    for (Eigen::Index j = 0; j < n; ++j) tmp[j] = odot(x.data(), A.data() + j, n, 1, n);
  } else {
    Eigen::Index at = 0;
    for (const auto &b : mblocks) {
      for (Eigen::Index k = 0; k < b.second; ++k, at += b.second)
        tmp[b.first + k] = odot(x.data() + b.first, mval.data() + at, b.second);
    }
  }
  return odot(tmp.data(), x.data(), n);
}

void omatmul(const MatrixXd &A, const MatrixXd &X, MatrixXd &Y) {
  const Eigen::Index r = A.rows(), n = A.cols(), c = X.cols();
  Y.resize(r, c);
  if (n == 0) {
    Y.setZero();
    return;
  }
  for (Eigen::Index j = 0; j < c; ++j) {
    double *y = Y.col(j).data();
    const double *a0 = A.col(0).data();
    const double x0 = X(0, j);
    for (Eigen::Index i = 0; i < r; ++i) y[i] = a0[i] * x0;
    for (Eigen::Index k = 1; k < n; ++k) {
      const double *a = A.col(k).data();
      const double xk = X(k, j);
      for (Eigen::Index i = 0; i < r; ++i) y[i] = y[i] + a[i] * xk;
    }
    for (Eigen::Index i = 0; i < r; ++i) y[i] = y[i] + 0.0;
  }
}
// sums.ordered(A, x) for a matrix A and a vector x
VectorXd otimes(const MatrixXd &A, const VectorXd &x) {
  MatrixXd Y;
  omatmul(A, x, Y);
  return Y.col(0);
}
// sums.ordered(W.T, x)
VectorXd otimes_t(const MatrixXd &W, const VectorXd &x) {
  VectorXd y(W.cols());
  for (Eigen::Index i = 0; i < W.cols(); ++i) y[i] = W.rows() ? odot(W.col(i).data(), x.data(), W.rows()) : 0.0;
  return y;
}

// A finite matrix without a -0.0 entry (a contact-space G and its submatrices: every entry a sum ending + 0.0)
bool clean(const MatrixXd &A) {
  const double *a = A.data();
  for (Eigen::Index k = 0; k < A.size(); ++k)
    if (!std::isfinite(a[k]) || (a[k] == 0.0 && std::signbit(a[k]))) return false;
  return true;
}

// nonzeros.lu_factor's factor of a clean square matrix given by its rows' stored entries (column, value; an entry
// not stored is +0.0), made by sparse_lu_factor and applied by sparse_lu_apply; the work arrays kept from one
// factor to the next (their capacity: no allocation a move in active_set)
struct SparseLU {
  using I = Eigen::Index;
  // the rows by id (set them: set_size, then fill a[r]); after the factor, row at[i] holds U's row i (columns >= i)
  std::vector<std::vector<std::pair<I, double>>> a;
  std::vector<std::vector<I>> colrows;
  std::vector<std::vector<std::pair<I, double>>> ucol;  // U's column k above the diagonal: (row, value)
  std::vector<I> at, pos, slot, cand, swaps;
  std::vector<char> pneg;
  std::vector<double> diag;
  std::vector<I> sptr;  // step j's updates (row position, multiplier): steps[sptr[j] .. sptr[j + 1])
  std::vector<std::pair<I, double>> steps, prow, lo_part;
  std::vector<uint64_t> seen;  // update's marks: pivot row entries met in the row (== tick)
  uint64_t tick = 0;
  std::vector<I> stamp, flips, bflips, bstamp;  // sparse_lu_apply's
  // which factor this is (SparseCache): of G gen, its rows idx; the steps taken from the last factor
  bool valid = false;
  uint64_t gen = 0;
  std::vector<I> idx;
  I reused = 0;
  void set_size(I n) {
    if ((I)a.size() < n) a.resize((size_t)n), colrows.resize((size_t)n), ucol.resize((size_t)n);
    for (I r = 0; r < n; ++r) a[(size_t)r].clear();
    n_ = n;
  }
  I n_ = 0;
};

// nonzeros.lu_factor: lu_solve's elimination on a clean A (w.a) at a cost of the nonzeros and their fill instead of
// n^2 (n^3 without the skips). The factor gets the operations of the skip path only (a_ik - l a_jk with l, a_jk != 0:
// the others leave a_ik as it is, and no entry of A ever becomes -0.0): each step's pivot row, its multipliers, U.
// last, c, change: the factor of the same G's submatrix whose rows were these but for one, added at sorted place c
// (change +1) or dropped from it (-1): its first c steps taken where they pick the same pivot rows (band_lu_solve's
// prefix rule, docs/theory.md §2.8), the columns < c of w.a's rows then ignored but on an added row; where the
// rule fails, refill() sets w.a again and the whole elimination runs. false at a zero or non-finite pivot.
template <class Refill>
bool sparse_lu_factor(SparseLU &w, const SparseLU *last, Eigen::Index c, int change, Refill &&refill) {
  using I = Eigen::Index;
  const I n = w.n_;
  w.reused = 0;
  if (last && change == -1)
    for (I j = 0; j < c; ++j)
      if (last->swaps[(size_t)j] == c) {  // the dropped row was a pivot row
        last = nullptr;
        break;
      }
  if (!last || !change) c = 0, change = 0, last = nullptr;
  const I add = change == 1 ? c : -1;
  auto &a = w.a;
  auto &colrows = w.colrows;
  auto &at = w.at, &pos = w.pos, &slot = w.slot, &cand = w.cand;
  for (I r = 0; r < n; ++r) colrows[(size_t)r].clear();
  for (I r = 0; r < n; ++r) {
    auto &row = a[(size_t)r];
    if (c && r != add)  // the columns < c: the last factor's L and U
      row.erase(std::remove_if(row.begin(), row.end(), [c](const std::pair<I, double> &e) { return e.first < c; }),
                row.end());
    for (auto &e : row) colrows[(size_t)e.first].push_back(r);
  }
  at.resize((size_t)n), pos.resize((size_t)n), slot.assign((size_t)n, -1);
  for (I i = 0; i < n; ++i) at[(size_t)i] = pos[(size_t)i] = i;
  w.swaps.resize((size_t)n), w.pneg.resize((size_t)n), w.diag.resize((size_t)n);
  w.sptr.assign(1, 0), w.steps.clear();
  auto entry = [&](I r, I col) -> std::pair<I, double> * {
    for (auto &e : a[(size_t)r])
      if (e.first == col) return &e;
    return nullptr;
  };
  auto take = [&](I r, I col) {  // row r's entry at col removed: its value (+0.0 where none is stored)
    auto &row = a[(size_t)r];
    for (size_t t = 0; t < row.size(); ++t)
      if (row[t].first == col) {
        const double v = row[t].second;
        row[t] = row.back();
        row.pop_back();
        return v;
      }
    return 0.0;
  };
  // a pivot row's entries pr by column (slot: an entry's place in pr, -1 elsewhere), set once for the rows a step
  // updates; update(r, l, pr): a_rk - l a_jk over pr's columns, row r's entries in place and its fill appended in
  // pr's order (each entry one operation, as in the dense elimination's skip path)
  auto scatter = [&](const std::vector<std::pair<I, double>> &pr, bool on) {
    for (size_t t = 0; t < pr.size(); ++t) slot[(size_t)pr[t].first] = on ? (I)t : -1;
    if (w.seen.size() < pr.size()) w.seen.resize(pr.size(), 0);
  };
  auto update = [&](I r, double l, const std::vector<std::pair<I, double>> &pr) {  // pr scattered
    auto &row = a[(size_t)r];
    const uint64_t tick = ++w.tick;
    for (auto &e : row) {
      const I t = slot[(size_t)e.first];
      if (t >= 0) e.second = e.second - l * pr[(size_t)t].second, w.seen[(size_t)t] = tick;
    }
    for (size_t t = 0; t < pr.size(); ++t)
      if (w.seen[t] != tick) {
        row.emplace_back(pr[t].first, 0.0 - l * pr[t].second);
        colrows[(size_t)pr[t].first].push_back(r);
      }
  };
  auto swap_rows = [&](I j, I p) {
    std::swap(at[(size_t)j], at[(size_t)p]);
    pos[(size_t)at[(size_t)j]] = j, pos[(size_t)at[(size_t)p]] = p;
  };
  auto &ucol = w.ucol;
  for (I k = c; k < n; ++k) ucol[(size_t)k].clear();
  auto &prow = w.prow, &lo_part = w.lo_part;
  if (c) {
    for (I k = 0; k < c; ++k) ucol[(size_t)k] = last->ucol[(size_t)k];  // U's columns < c: the last factor's
    for (I j = 0; j < c; ++j) {  // the last factor's steps j < c, on the columns >= c and an added row
      const I s0 = last->swaps[(size_t)j];
      const I p = s0 < c ? s0 : s0 + change;
      const double piv = last->diag[(size_t)j];
      if (add >= 0) {  // the added row (at c until step c) must not be step j's pivot row
        const auto *e = entry(add, j);
        const double v = e ? std::abs(e->second) : 0.0;
        if (!(v < std::abs(piv) || (v == std::abs(piv) && p < add))) {
          refill();
          return sparse_lu_factor(w, nullptr, 0, 0, refill);
        }
      }
      if (p != j) swap_rows(j, p);
      w.swaps[(size_t)j] = p, w.pneg[(size_t)j] = piv < 0.0, w.diag[(size_t)j] = piv;
      auto &rowj = a[(size_t)at[(size_t)j]];
      prow.clear();  // its columns >= c, as the steps before j left them (U's, final)
      for (auto &e : rowj)
        if (e.second != 0.0) prow.push_back(e);
      for (auto &e : prow) ucol[(size_t)e.first].emplace_back(j, e.second);
      lo_part.clear();
      for (auto &e : last->a[(size_t)last->at[(size_t)j]])  // U's row j in the columns < c: the last factor's
        if (e.first < c) {
          rowj.push_back(e);
          if (e.first > j && e.second != 0.0) lo_part.push_back(e);
        }
      scatter(prow, true);
      for (I t = last->sptr[(size_t)j]; t < last->sptr[(size_t)j + 1]; ++t) {
        I i = last->steps[(size_t)t].first;
        const double l = last->steps[(size_t)t].second;
        if (i == c && change == -1) continue;
        i = i < c ? i : i + change;
        if (l != 0.0 && !prow.empty()) update(at[(size_t)i], l, prow);
        w.steps.emplace_back(i, l);
      }
      scatter(prow, false);
      if (add >= 0 && entry(add, j)) {
        const double aij = take(add, j);
        if (aij != 0.0) {
          const double l = aij / piv;
          if (l != 0.0) {
            lo_part.insert(lo_part.end(), prow.begin(), prow.end());
            scatter(lo_part, true);
            update(add, l, lo_part);
            scatter(lo_part, false);
          }
          w.steps.emplace_back(add, l);
        }
      }
      w.sptr.push_back((I)w.steps.size());
    }
  }
  for (I j = c; j < n; ++j) {
    cand.clear();
    for (I r : colrows[(size_t)j])
      if (pos[(size_t)r] > j) cand.push_back(pos[(size_t)r]);
    std::sort(cand.begin(), cand.end());
    const auto *djj = entry(at[(size_t)j], j);
    I p = j;
    double best = djj ? std::abs(djj->second) : 0.0;
    for (I i : cand) {
      if (std::isnan(best)) break;
      const double v = std::abs(entry(at[(size_t)i], j)->second);
      if (std::isnan(v) || v > best) best = v, p = i;
    }
    const auto *pe = entry(at[(size_t)p], j);
    const double piv = pe ? pe->second : 0.0;
    if (!(piv != 0.0 && std::isfinite(piv))) return false;
    if (p != j) swap_rows(j, p);
    w.swaps[(size_t)j] = p, w.pneg[(size_t)j] = piv < 0.0, w.diag[(size_t)j] = piv;
    prow.clear();
    for (auto &e : a[(size_t)at[(size_t)j]])
      if (e.first > j && e.second != 0.0) prow.push_back(e);
    scatter(prow, true);
    for (I r : colrows[(size_t)j]) {
      const I i = pos[(size_t)r];
      if (i <= j) continue;
      const double aij = take(r, j);
      if (aij == 0.0) continue;  // l = +-0 with the pivot's sign: a flip of step j (sparse_lu_apply)
      const double l = aij / piv;
      if (l != 0.0) update(r, l, prow);
      w.steps.emplace_back(i, l);
    }
    scatter(prow, false);
    w.sptr.push_back((I)w.steps.size());
    for (auto &e : prow) ucol[(size_t)e.first].emplace_back(j, e.second);
  }
  w.reused = c;
  return true;
}
bool sparse_lu_factor(SparseLU &w) {
  return sparse_lu_factor(w, nullptr, 0, 0, [] {});
}

// nonzeros.lu_apply: x = A^-1 rhs by sparse_lu_factor's factor, the right-hand side getting every operation of the
// dense elimination, x_i - (+-0) x_j included, which leaves x_i as it is unless it is -0.0 and the product is -0.0
// (-0 - -0 = +0); those products (of the rows i with a_ij = 0, l = +-0 with the pivot's sign; of back substitution's
// a_ij = +0) are counted per step ("flips") and applied to an x_i when it is next operated on or read (a -0.0 turns
// +0.0 if a flip happened in between): x_j non-finite makes the dense result non-finite, so false
bool sparse_lu_apply(SparseLU &w, const VectorXd &rhs, VectorXd &x) {
  using I = Eigen::Index;
  const I n = w.n_;
  x = rhs;
  auto &stamp = w.stamp, &flips = w.flips;  // flips[s]: the flipping steps among 0 .. s-1
  stamp.assign((size_t)n, -1), flips.assign((size_t)n + 1, 0);
  auto settle = [&](I i, I j) {  // x at position i as the dense elimination has it before step j
    if (x[i] == 0.0 && std::signbit(x[i]) && flips[(size_t)j] - flips[(size_t)(stamp[(size_t)i] + 1)] > 0) x[i] = 0.0;
  };
  for (I j = 0; j < n; ++j) {
    const I p = w.swaps[(size_t)j];
    if (p != j) std::swap(x[j], x[p]), std::swap(stamp[(size_t)j], stamp[(size_t)p]);
    settle(j, j);
    const double xj = x[j];
    if (!std::isfinite(xj)) return false;
    flips[(size_t)j + 1] = flips[(size_t)j] + ((bool)w.pneg[(size_t)j] != std::signbit(xj));
    for (I t = w.sptr[(size_t)j]; t < w.sptr[(size_t)j + 1]; ++t) {
      const I i = w.steps[(size_t)t].first;
      settle(i, j);
      x[i] = x[i] - w.steps[(size_t)t].second * xj;
      stamp[(size_t)i] = j;
    }
  }
  auto &bflips = w.bflips, &bstamp = w.bstamp;  // bflips[s]: the flipping steps among s .. n-1
  bflips.assign((size_t)n + 1, 0), bstamp.assign((size_t)n, n);
  auto bsettle = [&](I i, I j) {  // before step j of back substitution
    if (x[i] == 0.0 && std::signbit(x[i]) && bflips[(size_t)j + 1] - bflips[(size_t)bstamp[(size_t)i]] > 0) x[i] = 0.0;
  };
  for (I j = n - 1; j >= 0; --j) {
    bsettle(j, j);
    x[j] = x[j] / w.diag[(size_t)j];
    if (!std::isfinite(x[j])) return false;
    bflips[(size_t)j] = bflips[(size_t)j + 1] + std::signbit(x[j]);
    for (auto &e : w.ucol[(size_t)j]) {
      bsettle(e.first, j);
      x[e.first] = x[e.first] - e.second * x[j];
      bstamp[(size_t)e.first] = j;
    }
  }
  return x.allFinite();
}

// x = A^-1 rhs on w.a's entries: the factor made and applied once (lu_solve; the active set's solves: sub_lu_solve)
bool sparse_lu_solve(SparseLU &w, const VectorXd &rhs, VectorXd &x) {
  return sparse_lu_factor(w) && sparse_lu_apply(w, rhs, x);
}

// lu_solve runs sparse_lu_solve on a clean matrix above kSparseLU rows with at most kSparseRow nonzeros a row on
// average (the same bits; below or denser, the dense loops cost less than the lists: ten boxes' G, ~24 a row)
constexpr Eigen::Index kSparseLU = 16, kSparseRow = 8;
// contact_space passes over every entry of MiW and G up to this many (nv m and m^2), over their lists above
constexpr Eigen::Index kScanEntries = Eigen::Index(1) << 16;
// Above kWideRows rows the active set's solves take the sparse factor (sub_lu_solve) up to kWideRow nonzeros a row of G on average:
// there band_lu_solve's k x k copies of G_AA a solve (and its O(k^2) loops) cost more than the lists (a 64-box
// pile, ~500 rows, ~30 a row); at ten boxes (76 rows, ~24 a row) the band's dense loops cost less
constexpr Eigen::Index kWideRows = 200, kWideRow = 64;

// qp._lu_solve: x = A^-1 rhs by Gaussian elimination with partial pivoting (the first largest |a_ij| of the
// column; a NaN in it: no pivot), then back substitution by columns, each entry with the same operations in the
// same order as the Python one (docs/theory.md §2.8: no LAPACK, no FMA); false at a zero or non-finite pivot,
// or when x is not finite
//
// Where A is finite and has no -0.0 entry (a contact-space G: every entry a sum ending + 0.0), the elimination skips
// the rows i with a_ij = 0 and the columns k with a_jk = 0: a_ik - (+-0) a_jk = a_ik there (no entry ever becomes
// -0.0, so not even a zero's sign changes), the same bits at a cost of the nonzeros (a stack's G is banded); the
// right-hand side gets every operation (its entries may be -0.0); above kSparseLU rows sparse_lu_solve does it on
// the nonzeros alone
bool lu_solve(const MatrixXd &A, const VectorXd &rhs, VectorXd &x, bool is_clean = false, bool dense = false) {
  const Eigen::Index n = A.rows();
  const bool skip = is_clean || clean(A);  // is_clean: the caller knows A finite, without -0.0
  if (skip && !dense && n > kSparseLU && (A.array() != 0.0).count() <= kSparseRow * n) {  // dense: the caller knows
    thread_local SparseLU w;
    w.set_size(n);
    for (Eigen::Index j = 0; j < n; ++j)
      for (Eigen::Index i = 0; i < n; ++i)
        if (A(i, j) != 0.0) w.a[(size_t)i].emplace_back(j, A(i, j));
    return sparse_lu_solve(w, rhs, x);
  }
  MatrixXd a = A;
  x = rhs;
  std::vector<Eigen::Index> cols;
  for (Eigen::Index j = 0; j < n; ++j) {
    Eigen::Index p = j;
    double best = std::abs(a(j, j));
    for (Eigen::Index i = j + 1; i < n && !std::isnan(best); ++i) {
      const double v = std::abs(a(i, j));
      if (std::isnan(v) || v > best) best = v, p = i;
    }
    const double piv = a(p, j);
    if (!(piv != 0.0 && std::isfinite(piv))) return false;
    if (p != j) {
      for (Eigen::Index k = j; k < n; ++k) std::swap(a(j, k), a(p, k));
      std::swap(x[j], x[p]);
    }
    if (skip) {
      cols.clear();
      for (Eigen::Index k = j + 1; k < n; ++k)
        if (a(j, k) != 0.0) cols.push_back(k);
    }
    for (Eigen::Index i = j + 1; i < n; ++i) {
      const double aij = a(i, j);  // skip: +0 / piv without the division
      const double l = skip && aij == 0.0 ? std::copysign(0.0, piv) : aij / piv;
      if (!skip)
        for (Eigen::Index k = j + 1; k < n; ++k) a(i, k) = a(i, k) - l * a(j, k);
      else if (l != 0.0)
        for (Eigen::Index k : cols) a(i, k) = a(i, k) - l * a(j, k);
      x[i] = x[i] - l * x[j];
    }
  }
  for (Eigen::Index j = n - 1; j >= 0; --j) {
    x[j] = x[j] / a(j, j);
    for (Eigen::Index i = 0; i < j; ++i) x[i] = x[i] - a(i, j) * x[j];
  }
  return x.allFinite();
}

// A contact-space G as active_set reads it, built once a projection (project: both passes of the active set and the
// final solves share it): finite, clean (lu_solve's skips: no -0.0), its largest |entry|, and (finite) its nonzeros by
// columns (cptr, cidx: the rows of each) and by rows (rptr, ridx, rval: each row's columns, ascending, and values,
// G's rows without its strided reads); the buffers kept from one projection to the next (no allocation)
struct GInfo {
  bool finite = false, is_clean = false, sparse = false;
  double gmax = 0.0;
  std::vector<Eigen::Index> cptr, cidx, rptr, ridx, fill;
  std::vector<double> rval;
  uint64_t gen = 0;  // which G this is: a number no other set() gives (band_lu_solve's factor cache is G's while it holds)
  // odot(G[p], x) over row p's nonzero terms (G and x finite: the others add +-0, settled by the + 0.0; nonzeros.Rows
  // .row_dot), x indexed through `at` (-1: outside x; null: x by G's columns)
  double row_dot(Eigen::Index p, const double *x, const Eigen::Index *at) const {
    double sum = 0.0;
    bool first = true;
    for (Eigen::Index t = rptr[(size_t)p]; t < rptr[(size_t)p + 1]; ++t) {
      const Eigen::Index c = at ? at[ridx[(size_t)t]] : ridx[(size_t)t];
      if (c < 0) continue;
      const double term = rval[(size_t)t] * x[c];
      sum = first ? term : sum + term;
      first = false;
    }
    return sum + 0.0;
  }
  static uint64_t next_gen() {
    static std::atomic<uint64_t> made{0};
    return ++made;
  }
  // one pass over G: finite, clean (no -0.0), its largest |entry| (exact: the same max in any order) and its
  // nonzeros by columns; where an entry is not finite, Eigen's max and no lists
  void set(const MatrixXd &G) {
    collect(G, [&](Eigen::Index, auto &&entry) {
      for (Eigen::Index i = 0; i < G.rows(); ++i)
        if (!entry(i)) return;
    });
  }
  // set(G) where G's entries outside the rows `rows` lists for each column (ptr, ascending; a superset of its
  // nonzeros) are +0.0: the same lists, flags and max, at the cost of the listed entries (contact_space's G)
  void set_listed(const MatrixXd &G, const std::vector<Eigen::Index> &ptr, const std::vector<Eigen::Index> &rows) {
    collect(G, [&](Eigen::Index k, auto &&entry) {
      for (Eigen::Index t = ptr[(size_t)k]; t < ptr[(size_t)k + 1]; ++t)
        if (!entry(rows[(size_t)t])) return;
    });
  }
  // set's pass over the entries each(k, entry) hands entry(i) for column k, ascending (false: not finite, stop)
  template <class Each> void collect(const MatrixXd &G, Each &&each) {
    gen = next_gen();
    const Eigen::Index m = G.rows();
    cptr.assign((size_t)m + 1, 0), rptr.assign((size_t)m + 1, 0), cidx.clear();
    bool fin = true, no_negative_zero = true;
    double top = 0.0;
    for (Eigen::Index k = 0; k < m && fin; ++k) {
      const double *g = G.col(k).data();
      each(k, [&](Eigen::Index i) {
        const double v = g[i];
        if (v == 0.0) {
          no_negative_zero = no_negative_zero && !std::signbit(v);
          return true;
        }
        if (!std::isfinite(v)) return fin = false;
        top = std::max(top, std::abs(v));
        cidx.push_back(i), ++rptr[(size_t)i + 1];
        return true;
      });
      cptr[(size_t)k + 1] = (Eigen::Index)cidx.size();
    }
    finish(G, fin, no_negative_zero, top);
  }
  void finish(const MatrixXd &G, bool fin, bool no_negative_zero, double top) {
    const Eigen::Index m = G.rows();
    finite = fin;
    if (!finite) cptr.assign((size_t)m + 1, 0), rptr.assign((size_t)m + 1, 0), cidx.clear();
    gmax = finite && m > 0 ? top : G.cwiseAbs().maxCoeff();
    is_clean = finite && no_negative_zero;
    if (finite) {
      for (Eigen::Index i = 0; i < m; ++i) rptr[(size_t)i + 1] += rptr[(size_t)i];
      ridx.resize(cidx.size()), rval.resize(cidx.size());
      fill.assign(rptr.begin(), rptr.end() - 1);
      for (Eigen::Index k = 0; k < m; ++k)
        for (Eigen::Index t = cptr[(size_t)k]; t < cptr[(size_t)k + 1]; ++t) {
          const Eigen::Index i = cidx[(size_t)t], at = fill[(size_t)i]++;
          ridx[(size_t)at] = k, rval[(size_t)at] = G(i, k);
        }
    }
    const size_t nnz = cidx.size();  // G_AA's solves on its nonzeros (sub_lu_solve; kWideRows)
    sparse = is_clean && (nnz <= (size_t)(kSparseRow * m) || (m > kWideRows && nnz <= (size_t)(kWideRow * m)));
  }
};

// lu_solve(G_AA, rhs, x, true, true)'s bits (the dense elimination with its skips) for a submatrix G_AA of a clean G
// (gi.is_clean; A: idx, ascending; pos: a row's place in idx, -1 outside A), on a row-major copy of G_AA: row i's
// update by the pivot row j runs over the columns j < k < hi_j (hi_j: past row j's last nonzero, fill included),
// contiguous, instead of the list of row j's nonzero columns. Where a_jk = +0 in that range, a_ik - l a_jk = a_ik:
// l is finite (|l| <= 1 by the partial pivoting) and no entry of a clean matrix is or becomes -0.0 (lu_solve's
// comment), so the bits are the skips'. A row i with no nonzero before column lo_i has a_ij = +0 for j < lo_i (an
// update needs a_ij != 0), which no pivot search can pick. The buffers kept from one solve to the next.
//
// The factor's prefix kept from one solve to the next (docs/theory.md §2.8): the active set's consecutive solves are
// of the same G with one row and column of A added at sorted place c, or dropped from it. Step j of the elimination
// reads and writes column j and the columns right of it, and leaves column j as it is from then on (its
// multipliers a_ij, i > j, stay where step j made them: no later swap moves them), so after c steps the columns < c
// hold L's and U's entries, final. Where the last factor (w.a) is of the same G (gi.gen) and its rows were idx but
// for that one, and steps 0 .. c-1 pick the same pivot rows, those columns are the last factor's, its rows at c and
// below moved by one place: an added row at c is not step j's pivot row iff |a_cj| (after the steps before j) is
// below the pivot's |a_pj|, or equal with the pivot row p above c (the first largest wins; a non-finite a_cj
// fails); a dropped row must not have been a pivot row of steps j < c. Steps j < c are then done again on the
// columns >= c only (and on an added row, every column: its multipliers are new), the right-hand side as always,
// and the steps from c on as always: each entry gets the same operations in the same order as in the whole
// elimination, which runs where any of this does not hold. w.reused: the steps taken from the last factor.
struct BandLU {
  std::vector<double> a, b;  // a: the last factor (row-major n x n: U on and above the diagonal, step j's a_ij below
                             // it); b: the one being made
  std::vector<Eigen::Index> lo, hi;
  // G_AA itself (row-major) and its rows' first nonzero and past their last (lo, hi before any step): the last
  // factor's (g, glo, ghi) and the one being made's (g2, glo2, ghi2)
  std::vector<double> g, g2;
  std::vector<Eigen::Index> glo, ghi, glo2, ghi2;
  bool valid = false;  // a holds a complete factor: of G gen, rows idx, step j's pivot row prow[j] and pivot piv[j]
  uint64_t gen = 0;
  std::vector<Eigen::Index> idx, prow;
  std::vector<double> piv;
  Eigen::Index reused = 0;
};
bool band_lu_solve(BandLU &w, const GInfo &gi, const std::vector<Eigen::Index> &idx, const Eigen::Index *pos,
                   const VectorXd &rhs, VectorXd &x) {
  using I = Eigen::Index;
  const I n = (I)idx.size();
  // the prefix: c steps, and the row that differs (change +1: idx[c] added, -1: the last factor's row c dropped,
  // 0: the same rows, c = n)
  I c = 0;
  int change = 0;
  if (w.valid && w.gen == gi.gen) {
    const I n0 = (I)w.idx.size();
    const I *o = w.idx.data(), *q = idx.data();
    I k = 0;
    while (k < std::min(n, n0) && q[k] == o[k]) ++k;
    if (n == n0 && k == n) c = n;
    else if (n == n0 + 1 && std::equal(q + k + 1, q + n, o + k)) c = k, change = 1;
    else if (n + 1 == n0 && std::equal(q + k, q + n, o + k + 1)) c = k, change = -1;
    if (change == -1)
      for (I j = 0; j < c; ++j)
        if (w.prow[(size_t)j] == c) c = 0;  // the dropped row was a pivot row
    if (c == 0) change = 0;
  }
  w.valid = false;
  while (true) {
    const I add = change == 1 ? c : -1;  // the added row's place (-1: none)
    auto to_new = [&](I i0) { return i0 < c ? i0 : i0 + change; };  // a row of the last factor in this one
    // G_AA itself (g2) and each row's first and last nonzero (glo2, ghi2: lo_i, hi_i before any step): the last
    // one's (g, glo, ghi) with the row and column added or dropped, where the prefix is kept; else from G's rows
    w.g2.assign((size_t)(n * n), 0.0), w.glo2.assign((size_t)n, n), w.ghi2.assign((size_t)n, 0);
    double *g2 = w.g2.data();
    I *glo = w.glo2.data(), *ghi = w.ghi2.data();
    auto scan = [&](I i) {  // row i of G_AA from G's row idx[i]
      const I r = idx[(size_t)i];
      for (I t = gi.rptr[(size_t)r]; t < gi.rptr[(size_t)r + 1]; ++t) {
        const I col = pos[gi.ridx[(size_t)t]];
        if (col < 0) continue;
        g2[i * n + col] = gi.rval[(size_t)t];
        glo[i] = std::min(glo[i], col), ghi[i] = std::max(ghi[i], col + 1);
      }
    };
    if (c == 0) {
      for (I i = 0; i < n; ++i) scan(i);
    } else {
      const I n0 = (I)w.idx.size();
      const double *g0 = w.g.data();
      for (I i = 0; i < n; ++i) {
        if (i == add) continue;
        const I i0 = i < c ? i : i - change;  // its row in the last G_AA
        std::copy(g0 + i0 * n0, g0 + i0 * n0 + c, g2 + i * n);
        std::copy(g0 + i0 * n0 + c + (change == -1), g0 + i0 * n0 + n0, g2 + i * n + c + (change == 1));
        const I l0 = w.glo[(size_t)i0], h0 = w.ghi[(size_t)i0];
        if (change == 1) {
          glo[i] = l0 < c ? l0 : l0 + 1, ghi[i] = h0 <= c ? h0 : h0 + 1;
        } else if (change == -1 && (l0 == c || h0 == c + 1)) {  // the dropped column was its first or last
          for (I k = 0; k < n; ++k)
            if (g2[i * n + k] != 0.0) glo[i] = std::min(glo[i], k), ghi[i] = k + 1;
        } else {
          glo[i] = l0 <= c ? l0 : l0 + change, ghi[i] = h0 <= c ? h0 : h0 + change;
        }
      }
      if (add >= 0) {  // the added row (G's row idx[c]) and column (G's column idx[c], its values from G's rows)
        scan(add);
        const I col = idx[(size_t)add];
        for (I t = gi.cptr[(size_t)col]; t < gi.cptr[(size_t)col + 1]; ++t) {
          const I r = gi.cidx[(size_t)t], i = pos[r];
          if (i < 0 || i == add) continue;
          const auto *b = gi.ridx.data() + gi.rptr[(size_t)r], *e = gi.ridx.data() + gi.rptr[(size_t)r + 1];
          g2[i * n + add] = gi.rval[(size_t)(std::lower_bound(b, e, col) - gi.ridx.data())];
          glo[i] = std::min(glo[i], add), ghi[i] = std::max(ghi[i], add + 1);
        }
      }
    }
    w.b.assign(w.g2.begin(), w.g2.end()), w.lo.assign(glo, glo + n), w.hi.assign(ghi, ghi + n);
    double *a = w.b.data();
    I *lo = w.lo.data(), *hi = w.hi.data();
    x = rhs;
    bool same = true;  // steps 0 .. c-1 pick the last factor's pivot rows
    // elimination step j on pivot row p (value piv): rows j and p swapped from column `from` on, then each row i
    // below updated from column first(i) on (the dense lu_solve's operations, in its order)
    auto eliminate = [&](I j, I p, double piv, I from, auto first) {
      if (p != j) {
        const I e = std::max(hi[j], hi[p]);  // both rows +0 from column e on
        for (I k = from; k < e; ++k) std::swap(a[j * n + k], a[p * n + k]);
        std::swap(lo[j], lo[p]), std::swap(hi[j], hi[p]);
        std::swap(x[j], x[p]);
      }
      const double *rj = a + j * n;
      const I hj = hi[j];
      const double xj = x[j];
      for (I i = j + 1; i < n; ++i) {
        double *ri = a + i * n;
        const double aij = ri[j];
        const double l = aij == 0.0 ? std::copysign(0.0, piv) : aij / piv;
        if (l != 0.0) {
          for (I k = first(i); k < hj; ++k) ri[k] = ri[k] - l * rj[k];
          hi[i] = std::max(hi[i], hj);
        }
        x[i] = x[i] - l * xj;
      }
    };
    if (c > 0) {
      const I n0 = (I)w.idx.size();
      const double *a0 = w.a.data();
      for (I i0 = 0; i0 < n0; ++i0)
        if (!(change == -1 && i0 == c)) std::copy(a0 + i0 * n0, a0 + i0 * n0 + c, a + to_new(i0) * n);
      for (I j = 0; j < c && same; ++j) {  // steps j < c on the columns >= c, the added row and the right-hand side
        const I p = to_new(w.prow[(size_t)j]);
        const double piv = w.piv[(size_t)j];
        if (add >= 0) {
          const double v = std::abs(a[add * n + j]), best = std::abs(piv);
          if (!(v < best || (v == best && p < add))) {
            same = false;
            break;
          }
        }
        eliminate(j, p, piv, c, [&](I i) { return i == add ? j + 1 : std::max(c, j + 1); });
      }
      if (!same) {  // the whole elimination
        c = 0, change = 0;
        continue;
      }
      for (I j = 0; j < c; ++j) w.prow[(size_t)j] = to_new(w.prow[(size_t)j]);
    }
    w.prow.resize((size_t)n), w.piv.resize((size_t)n);
    for (I j = c; j < n; ++j) {
      I p = j;
      double best = std::abs(a[j * n + j]);
      for (I i = j + 1; i < n && !std::isnan(best); ++i) {
        if (lo[i] > j) continue;  // a_ij = +0
        const double v = std::abs(a[i * n + j]);
        if (std::isnan(v) || v > best) best = v, p = i;
      }
      const double piv = a[p * n + j];
      if (!(piv != 0.0 && std::isfinite(piv))) return false;
      w.prow[(size_t)j] = p, w.piv[(size_t)j] = piv;
      eliminate(j, p, piv, j, [j](I) { return j + 1; });
    }
    for (I j = n - 1; j >= 0; --j) {
      x[j] = x[j] / a[j * n + j];
      const double xj = x[j];
      for (I i = 0; i < j; ++i) x[i] = x[i] - a[i * n + j] * xj;
    }
    w.a.swap(w.b), w.g.swap(w.g2), w.glo.swap(w.glo2), w.ghi.swap(w.ghi2);
    w.valid = true, w.gen = gi.gen, w.idx = idx, w.reused = c;
    return x.allFinite();
  }
}

// The BandLU the active set's solves and project's final ones share (its factor prefix kept from one to the next:
// the final solve is of the active set's last rows and the row added last, or of the same rows)
BandLU &band_cache() {
  thread_local BandLU w;
  return w;
}

// sub_lu_solve's factors (qp._solve_nonzeros' G.factor): the last one made and the one being made
struct SparseCache {
  SparseLU f[2];
  int last = 0;
};

// w.a set to G_AA's nonzero entries from G's rows (A = sel; pos: a row's place in sel, -1 outside it), by rows,
// columns ascending (nonzeros.Rows.sub)
void fill_sub(SparseLU &w, const GInfo &gi, const std::vector<Eigen::Index> &sel, const Eigen::Index *pos) {
  const Eigen::Index k = (Eigen::Index)sel.size();
  w.set_size(k);
  for (Eigen::Index i = 0; i < k; ++i)
    for (Eigen::Index t = gi.rptr[(size_t)sel[(size_t)i]]; t < gi.rptr[(size_t)sel[(size_t)i] + 1]; ++t)
      if (pos[gi.ridx[(size_t)t]] >= 0) w.a[(size_t)i].emplace_back(pos[gi.ridx[(size_t)t]], gi.rval[(size_t)t]);
}

// nonzeros.one_apart: (c, +1) where the ascending rows idx are old with one added at place c, (c, -1) where one was
// dropped from old's place c, else (0, 0)
std::pair<Eigen::Index, int> one_apart(const std::vector<Eigen::Index> &old, const std::vector<Eigen::Index> &idx) {
  const size_t n = std::min(old.size(), idx.size());
  size_t c = 0;
  while (c < n && idx[c] == old[c]) ++c;
  if (idx.size() == old.size() + 1 && std::equal(idx.begin() + (std::ptrdiff_t)c + 1, idx.end(), old.begin() + (std::ptrdiff_t)c))
    return {(Eigen::Index)c, 1};
  if (idx.size() + 1 == old.size() && std::equal(idx.begin() + (std::ptrdiff_t)c, idx.end(), old.begin() + (std::ptrdiff_t)c + 1))
    return {(Eigen::Index)c, -1};
  return {0, 0};
}

// lu_solve(G[sel][:, sel], rhs, x)'s bits by sparse_lu_factor on G_AA's nonzeros, from G's rows (gi: G clean; pos:
// a row's place in sel, -1 outside it), as qp._solve_nonzeros: the last factor applied again where the rows are the
// same (the start's, the final and the refinement's solves), its first steps taken where they differ by one row
// added or dropped (the active set's moves; sparse_lu_factor's prefix rule); cache.f[cache.last].reused: the steps
// taken from the factor before
bool sub_lu_solve(SparseCache &cache, const GInfo &gi, const std::vector<Eigen::Index> &sel, const Eigen::Index *pos,
                  const VectorXd &rhs, VectorXd &x) {
  using I = Eigen::Index;
  SparseLU &last = cache.f[cache.last];
  const I k = (I)sel.size();
  const bool same_g = last.valid && last.gen == gi.gen;
  if (same_g && last.idx == sel) {
    last.reused = k;
    return sparse_lu_apply(last, rhs, x);
  }
  SparseLU &w = cache.f[1 - cache.last];
  auto fill = [&] { fill_sub(w, gi, sel, pos); };
  fill();
  const auto [c, change] = same_g ? one_apart(last.idx, sel) : std::pair<I, int>{0, 0};
  const bool ok = sparse_lu_factor(w, same_g && change && c ? &last : nullptr, c, change, fill);
  cache.last = 1 - cache.last;
  w.valid = ok, w.gen = gi.gen, w.idx = sel;
  return ok && sparse_lu_apply(w, rhs, x);
}
bool sub_lu_solve(const GInfo &gi, const std::vector<Eigen::Index> &sel, const Eigen::Index *pos, const VectorXd &rhs,
                  VectorXd &x) {
  thread_local SparseCache cache;
  return sub_lu_solve(cache, gi, sel, pos, rhs, x);
}

bool solve_sub(const MatrixXd &G, const GInfo &gi, const std::vector<Eigen::Index> &sel, const VectorXd &rhs,
               VectorXd &x, bool fresh = false);

// schur.py: the active set's solves of more than kSchurMinRows rows on a G of more than kWideRows rows (gi.sparse)
// by the factor of a base set B and a Schur complement where A is B with at most kSchurRows rows added or dropped,
// else A factored as the new base (docs/theory.md §1.3); one base a thread (schur.py's _held), of one G (gi.gen)
constexpr Eigen::Index kSchurMinRows = 32, kSchurRows = 40;
struct SchurCache {
  bool valid = false;
  uint64_t gen = 0;
  std::vector<Eigen::Index> B, pos;  // the base's rows (ascending) and a row's place in B (-1 outside it)
  SparseLU f;                        // B's factor
  std::map<std::pair<Eigen::Index, bool>, VectorXd> cols;  // z = G_BB^-1 G_Bp (row p added) or G_BB^-1 e_d (dropped)
};

// schur.py's _held flags of this thread: used (a solve went through schur_solve since project's polish began), off
// (its second try: direct factors alone)
struct SchurFlags {
  bool used = false, off = false;
};
SchurFlags &schur_state() {
  thread_local SchurFlags f;
  return f;
}

bool schur_applies(const GInfo &gi, Eigen::Index m, Eigen::Index k) {
  return gi.sparse && m > kWideRows && k > kSchurMinRows && !schur_state().off;
}

// schur.solve: x = G_AA^-1 rhs (A = sel, ascending), false where schur.solve returns None
bool schur_solve(const MatrixXd &G, const GInfo &gi, const std::vector<Eigen::Index> &sel, const VectorXd &rhs,
                 VectorXd &x, bool fresh = false) {
  using I = Eigen::Index;
  thread_local SchurCache sc;
  thread_local std::vector<I> P, D;
  thread_local std::vector<char> kept;
  const I m = G.rows(), k = (I)sel.size();
  schur_state().used = true;
  bool have = sc.valid && sc.gen == gi.gen && (!fresh || sc.B == sel);  // (fresh: A's own factor; the base's if A is it)
  if (have) {
    P.clear(), D.clear();
    kept.assign((size_t)m, 0);
    for (I r : sel) {
      kept[(size_t)r] = 1;
      if (sc.pos[(size_t)r] < 0) P.push_back(r);
    }
    for (I r : sc.B)
      if (!kept[(size_t)r]) D.push_back(r);
    have = (I)(P.size() + D.size()) <= kSchurRows;
  }
  if (!have) {  // A becomes the base: factored
    sc.valid = false;
    sc.cols.clear();
    sc.B = sel;
    sc.pos.assign((size_t)m, -1);
    for (I i = 0; i < k; ++i) sc.pos[(size_t)sel[(size_t)i]] = i;
    fill_sub(sc.f, gi, sel, sc.pos.data());
    if (!sparse_lu_factor(sc.f)) return false;
    sc.valid = true, sc.gen = gi.gen;
    return sparse_lu_apply(sc.f, rhs, x);
  }
  if (P.empty() && D.empty()) return sparse_lu_apply(sc.f, rhs, x);
  const I nB = (I)sc.B.size(), nP = (I)P.size(), n = nP + (I)D.size();
  const auto &pos = sc.pos;
  VectorXd yB = VectorXd::Zero(nB), y(nP), w;
  for (I i = 0, ip = 0; i < k; ++i) {
    const I at = pos[(size_t)sel[(size_t)i]];
    if (at >= 0) yB[at] = rhs[i];
    else y[ip++] = rhs[i];
  }
  if (!sparse_lu_apply(sc.f, yB, w)) return false;
  std::vector<const VectorXd *> Z((size_t)n);
  for (I j = 0; j < n; ++j) {  // made once per base
    const std::pair<I, bool> key = j < nP ? std::make_pair(P[(size_t)j], true) : std::make_pair(D[(size_t)(j - nP)], false);
    auto it = sc.cols.find(key);
    if (it == sc.cols.end()) {
      VectorXd c = VectorXd::Zero(nB), z;
      if (key.second)
        for (I i = 0; i < nB; ++i) c[i] = G(sc.B[(size_t)i], key.first);
      else
        c[pos[(size_t)key.first]] = 1.0;
      if (!sparse_lu_apply(sc.f, c, z)) return false;
      it = sc.cols.emplace(key, std::move(z)).first;
    }
    Z[(size_t)j] = &it->second;
  }
  auto row_dot = [&](I a, const VectorXd &z) { return gi.row_dot(a, z.data(), pos.data()); };
  MatrixXd S(n, n);
  VectorXd t(n), s;
  for (I i = 0; i < n; ++i) {
    if (i < nP) {  // row a added: G_aB x_B + G_aP x_P = y_a
      const I a = P[(size_t)i];
      for (I j = 0; j < n; ++j) {
        const double d = row_dot(a, *Z[(size_t)j]);
        S(i, j) = j < nP ? G(a, P[(size_t)j]) - d : -d;
      }
      t[i] = y[i] - row_dot(a, w);
    } else {  // row a dropped: held at 0
      const I pa = pos[(size_t)D[(size_t)(i - nP)]];
      for (I j = 0; j < n; ++j) S(i, j) = -(*Z[(size_t)j])[pa];
      t[i] = -w[pa];
    }
  }
  if (!lu_solve(S, t, s)) return false;
  for (I j = 0; j < n; ++j) {
    const VectorXd &z = *Z[(size_t)j];
    const double sj = s[j];
    for (I i = 0; i < nB; ++i) w[i] = w[i] - z[i] * sj;
  }
  x.resize(k);
  for (I i = 0, ip = 0; i < k; ++i) {
    const I at = pos[(size_t)sel[(size_t)i]];
    x[i] = at >= 0 ? w[at] : s[ip++];
  }
  return x.allFinite();
}

// qp._active_set (Goldfarb-Idnani's dual active set on min 1/2 lam'G lam - r'lam, lam >= 0), operation for
// operation, from nothing or from `start` (qp._active_set's act: the rows taken as active, lam_A = G_AA^-1 r_A, a
// start that is singular or has a negative multiplier: from nothing); false where qp._active_set returns None (the
// Python step then takes it, and piqp). gi: G's GInfo.
bool active_set(const Constants &C, const MatrixXd &G, const GInfo &gi, const VectorXd &r, double tol,
                std::vector<char> &act, VectorXd &lam, const std::vector<char> *start = nullptr) {
  const Eigen::Index m = r.size();
  const double inf = std::numeric_limits<double>::infinity();
  act.assign(m, 0);
  lam = VectorXd::Zero(m);
  if (start) {  // qp._active_set's warm start: lam_A = G_AA^-1 r_A, its negative rows dropped (docs/theory.md §1.3)
    std::vector<char> cur(*start);
    std::vector<Eigen::Index> sel;
    VectorXd rA, x;
    for (int pass = 0; pass < C.start_passes; ++pass) {
      sel.clear();
      for (Eigen::Index i = 0; i < m; ++i)
        if (cur[(size_t)i]) sel.push_back(i);
      if (sel.empty()) break;
      rA.resize((Eigen::Index)sel.size());
      for (size_t i = 0; i < sel.size(); ++i) rA[(Eigen::Index)i] = r[sel[i]];
      if (!solve_sub(G, gi, sel, rA, x)) break;  // singular: from nothing
      bool neg = false;
      for (size_t i = 0; i < sel.size(); ++i)
        if (x[(Eigen::Index)i] < 0.0) cur[(size_t)sel[i]] = 0, neg = true;
      if (!neg) {
        for (size_t i = 0; i < sel.size(); ++i) act[(size_t)sel[i]] = 1, lam[sel[i]] = x[(Eigen::Index)i];
        break;
      }
    }
  }
  int moves = 0;
  const double gmax = gi.gmax;
  thread_local std::vector<Eigen::Index> idx;
  thread_local VectorXd d, rhs, Gp, s;
  thread_local MatrixXd GA;
  idx.clear();
  s.resize(m);
  const bool finite = gi.finite, is_clean = gi.is_clean;  // lu_solve on G's submatrices: finite, no -0.0
  const auto &cptr = gi.cptr, &cidx = gi.cidx;
  const bool sparse = gi.sparse;  // G_AA's solves on its nonzeros
  BandLU &band = band_cache();  // G_AA row-major, for band_lu_solve (G clean)
  thread_local std::vector<Eigen::Index> posA;  // a row's place in idx, -1 outside A (reset where idx was set)
  posA.assign(finite ? (size_t)m : 0, -1);
  bool lam_finite = lam.allFinite();
  auto row_dot = [&](Eigen::Index p, const double *x, const Eigen::Index *at) { return gi.row_dot(p, x, at); };
  while (true) {
    if (finite && lam_finite) {  // G @ lam - r: the terms with lam_k = +-0 or G_ik = 0 add +-0 (a zero's sign settled by the + 0.0)
      s.setZero();
      for (Eigen::Index k = 0; k < m; ++k) {
        const double lk = lam[k];
        if (lk == 0.0) continue;
        const double *g = G.col(k).data();
        for (Eigen::Index t = cptr[(size_t)k]; t < cptr[(size_t)k + 1]; ++t) {
          const Eigen::Index i = cidx[(size_t)t];
          s[i] = s[i] + g[i] * lk;
        }
      }
      for (Eigen::Index i = 0; i < m; ++i) s[i] = (s[i] + 0.0) - r[i];
    } else {
      s = otimes(G, lam) - r;
    }
    Eigen::Index p = 0;
    double best = act[0] ? inf : s[0];
    for (Eigen::Index i = 1; i < m; ++i) {
      const double si = act[i] ? inf : s[i];
      if (si < best) best = si, p = i;
    }
    if (best >= -tol) return true;
    while (true) {  // add p, dropping the rows whose multipliers reach zero on the way
      if (++moves > C.moves_per_row * m + C.moves_extra) return false;
      if (finite)
        for (Eigen::Index i : idx) posA[(size_t)i] = -1;
      idx.clear();
      for (Eigen::Index i = 0; i < m; ++i)
        if (act[i]) idx.push_back(i);
      const Eigen::Index k = (Eigen::Index)idx.size();
      double z;
      if (k) {
        rhs.resize(k);
        for (Eigen::Index i = 0; i < k; ++i) rhs[i] = -G(idx[i], p);
        if (finite)
          for (Eigen::Index i = 0; i < k; ++i) posA[(size_t)idx[i]] = i;
        if (schur_applies(gi, m, k)) {  // schur.py: a factored base and a Schur complement
          if (!schur_solve(G, gi, idx, rhs, d)) return false;
        } else if (sparse && k > kSparseLU) {  // lu_solve's bits from G_AA's nonzeros
          if (!sub_lu_solve(gi, idx, posA.data(), rhs, d)) return false;
        } else if (is_clean) {  // lu_solve's bits on G_AA row-major, its updates over each pivot row's band
          if (!band_lu_solve(band, gi, idx, posA.data(), rhs, d)) return false;
        } else {
          GA.resize(k, k);
          for (Eigen::Index i = 0; i < k; ++i)
            for (Eigen::Index j = 0; j < k; ++j) GA(i, j) = G(idx[i], idx[j]);
          if (!lu_solve(GA, rhs, d, is_clean, true)) return false;
        }
        if (finite) {  // G[p, A] @ d (d finite: lu_solve checked)
          z = G(p, p) + row_dot(p, d.data(), posA.data());
        } else {
          Gp.resize(k);
          for (Eigen::Index i = 0; i < k; ++i) Gp[i] = G(p, idx[i]);
          z = G(p, p) + odot(Gp.data(), d.data(), k);
        }
      } else {
        d.resize(0);
        z = G(p, p);
      }
      const double sp = (finite && lam_finite ? row_dot(p, lam.data(), nullptr) : odot(&G(p, 0), lam.data(), m, m, 1)) -
                        r[p];  // G[p] @ lam - r[p]
      const double t1 = z > C.dependent * G(p, p) ? -sp / z : inf;
      double t2 = inf;
      Eigen::Index kk = -1;
      for (Eigen::Index j = 0; j < k; ++j) {
        if (!(d[j] < 0.0)) continue;
        const double ratio = lam[idx[j]] / -d[j];
        if (kk < 0 || ratio < t2) t2 = ratio, kk = idx[j];
      }
      if (t1 == inf && t2 == inf)  // p depends on A and no multiplier of A can shrink: met to round-off, or not
        return lam[p] == 0.0 && sp >= -(tol + C.met * (double)m * gmax * lam.maxCoeff());
      if (!(t1 <= t2) && kk < 0) return false;  // t1 NaN, no row to drop (qp._active_set: None; was a write at -1)
      const double t = t1 <= t2 ? t1 : t2;
      for (Eigen::Index j = 0; j < k; ++j) lam[idx[j]] = lam[idx[j]] + t * d[j];
      lam[p] = lam[p] + t;
      // np.maximum(lam, 0.0) on the entries just moved (A and p): every other one is +0.0 (never moved, or set at its
      // drop) or clamped at an earlier move, and the clamp leaves a clamped entry as it is; so is lam_finite
      for (Eigen::Index j = 0; j < k; ++j) {
        double &l = lam[idx[j]];
        l = std::max(l, 0.0), lam_finite = lam_finite && std::isfinite(l);
      }
      lam[p] = std::max(lam[p], 0.0), lam_finite = lam_finite && std::isfinite(lam[p]);
      if (t1 <= t2) {
        act[p] = 1;
        break;
      }
      lam[kk] = 0.0;
      act[kk] = 0;
    }
  }
}

// W's nonzeros by columns (wptr, widx: the velocities each contact's row moves) and whether W is finite, built once
// a projection (project); the buffers kept from one projection to the next
struct WInfo {
  bool finite = false;
  std::vector<Eigen::Index> wptr, widx;
  void set(const MatrixXd &W) {
    const Eigen::Index nv = W.rows(), m = W.cols();
    finite = W.allFinite();
    wptr.assign((size_t)m + 1, 0), widx.clear();
    for (Eigen::Index j = 0; j < m && finite; ++j) {
      for (Eigen::Index k = 0; k < nv; ++k)
        if (W(k, j) != 0.0) widx.push_back(k);
      wptr[(size_t)j + 1] = (Eigen::Index)widx.size();
    }
  }
  // max |W_ij| (W.cwiseAbs().maxCoeff(): the same max over the nonzeros where W is finite and has one)
  double abs_max(const MatrixXd &W) const {
    if (!finite || widx.empty()) return W.size() ? W.cwiseAbs().maxCoeff() : 0.0;
    double top = 0.0;
    for (Eigen::Index j = 0; j < W.cols(); ++j)
      for (Eigen::Index t = wptr[(size_t)j]; t < wptr[(size_t)j + 1]; ++t) top = std::max(top, std::abs(W(widx[(size_t)t], j)));
    return top;
  }
};

// otimes_t(W, x) (sums.ordered(W.T, x)) over W's nonzero terms where W and x are finite (a term with W_kj = +-0 adds
// +-0 to the sum: the same sum, its sign as a zero settled by the + 0.0; contact_space's argument), else otimes_t
// odot(W.col(j), x) over column j's nonzero terms (W and x finite: otimes_t_nz's argument)
inline double wcol_dot(const MatrixXd &W, const WInfo &wi, Eigen::Index j, const VectorXd &x) {
  const double *w = W.col(j).data();
  double sum = 0.0;
  bool first = true;
  for (Eigen::Index t = wi.wptr[(size_t)j]; t < wi.wptr[(size_t)j + 1]; ++t) {
    const Eigen::Index k = wi.widx[(size_t)t];
    const double term = w[k] * x[k];
    sum = first ? term : sum + term;
    first = false;
  }
  return sum + 0.0;
}
void otimes_t_nz(const MatrixXd &W, const WInfo &wi, const VectorXd &x, VectorXd &y) {
  if (!wi.finite || !x.allFinite() || W.rows() == 0) {
    y = otimes_t(W, x);
    return;
  }
  y.resize(W.cols());
  for (Eigen::Index j = 0; j < W.cols(); ++j) y[j] = wcol_dot(W, wi, j, x);
}

// MiW = Minv @ W and G = W.T @ MiW as omatmul sums them (k ascending, + 0.0), over the nonzero terms only: a term
// with a zero factor adds +-0 to the sum (the same sum; its sign as a zero settled by the + 0.0), so where Minv and W
// are finite this gives omatmul's bits at the cost of the nonzeros (M block diagonal over the trees, a row of W
// nonzero on the two bodies of its contact: docs/theory.md §2.8); anything non-finite takes omatmul itself. wi: W's
// WInfo; the nonzero lists in flat buffers kept from one call to the next (no allocation)
void contact_space(const MatrixXd &Minv, const MatrixXd &W, const WInfo &wi, MatrixXd &MiW, MatrixXd &G,
                   WInfo &mi, GInfo &gi, const Blocks *blocks = nullptr) {
  const Eigen::Index nv = W.rows(), m = W.cols();
  using I = Eigen::Index;
  // blocks: Minv's diagonal blocks (first row, size) in order, covering 0..nv, Minv +0.0 off them (the forest's M^-1:
  // docs/theory.md §2.12); none: one block, all of Minv
  const Blocks all{{0, nv}};
  const Blocks &B = blocks ? *blocks : all;
  bool finite = wi.finite;
  for (size_t b = 0; b < B.size() && finite; ++b) finite = Minv.block(B[b].first, B[b].first, B[b].second, B[b].second).allFinite();
  // MiW and G are +0.0 outside the entries the last call listed (mi's lists, G's nonzeros), where `kept` says so
  // and they are the same matrices of the same sizes: those entries are reset, not the whole of them
  thread_local bool kept = false;
  thread_local const double *kept_at[2] = {nullptr, nullptr};
  const bool reuse = kept && MiW.rows() == nv && MiW.cols() == m && G.rows() == m && G.cols() == m &&
                     kept_at[0] == MiW.data() && kept_at[1] == G.data();
  kept = false;
  if (!finite) {
    mi.finite = false;
    omatmul(Minv, W, MiW);
    omatmul(W.transpose(), MiW, G);
    gi.set(G);
    return;
  }
  if (reuse) {
    for (I j = 0; j < m; ++j) {
      double *y = MiW.col(j).data(), *gj = G.col(j).data();
      for (I t = mi.wptr[(size_t)j]; t < mi.wptr[(size_t)j + 1]; ++t) y[mi.widx[(size_t)t]] = 0.0;
      for (I t = gi.cptr[(size_t)j]; t < gi.cptr[(size_t)j + 1]; ++t) gj[gi.cidx[(size_t)t]] = 0.0;
    }
  } else {
    MiW.setZero(nv, m), G.setZero(m, m);
  }
  mi.finite = false;
  // small problems pass over every entry (a scan costs less than sorting the lists); larger ones over the lists,
  // sorted: the same sums, k ascending, the same bits
  const bool scan = nv * m <= kScanEntries && m * m <= kScanEntries;
  thread_local std::vector<I> mptr, midx, rptr, rcol, fill;  // Minv's nonzeros by columns; W's by rows (rptr, rcol, rval)
  thread_local std::vector<double> rval;
  mptr.assign((size_t)nv + 1, 0), midx.clear();
  for (const auto &bk : B)
    for (I k = bk.first; k < bk.first + bk.second; ++k) {
      for (I i = bk.first; i < bk.first + bk.second; ++i)
        if (Minv(i, k) != 0.0) midx.push_back(i);
      mptr[(size_t)k + 1] = (I)midx.size();
    }
  const auto &wptr = wi.wptr, &widx = wi.widx;
  thread_local std::vector<I> seen;  // the column j a row was last listed for (-1: none)
  seen.assign((size_t)nv, -1);
  mi.wptr.assign((size_t)m + 1, 0), mi.widx.clear();
  for (I j = 0; j < m; ++j) {
    double *y = MiW.col(j).data();
    for (I t = wptr[(size_t)j]; t < wptr[(size_t)j + 1]; ++t) {
      const I k = widx[(size_t)t];
      const double xk = W(k, j);
      const double *a = Minv.col(k).data();
      for (I s = mptr[(size_t)k]; s < mptr[(size_t)k + 1]; ++s) {
        const I i = midx[(size_t)s];
        y[i] = y[i] + a[i] * xk;
        if (seen[(size_t)i] != j) seen[(size_t)i] = j, mi.widx.push_back(i);
      }
    }
    mi.wptr[(size_t)j + 1] = (I)mi.widx.size();
    if (scan) {
      for (I i = 0; i < nv; ++i) y[i] = y[i] + 0.0;
      continue;
    }
    // the rows listed ascending (G's sums below run over k ascending); y's other entries are +0.0 (setZero)
    std::sort(mi.widx.begin() + mi.wptr[(size_t)j], mi.widx.end());
    for (I t = mi.wptr[(size_t)j]; t < mi.wptr[(size_t)j + 1]; ++t) y[mi.widx[(size_t)t]] = y[mi.widx[(size_t)t]] + 0.0;
  }
  mi.finite = true;  // MiW's entries outside a column's list are +0.0
  // each row of W: (column, value), columns ascending
  rptr.assign((size_t)nv + 1, 0);
  for (I t = 0; t < (I)widx.size(); ++t) ++rptr[(size_t)widx[(size_t)t] + 1];
  for (I k = 0; k < nv; ++k) rptr[(size_t)k + 1] += rptr[(size_t)k];
  rcol.resize(widx.size()), rval.resize(widx.size());
  fill.assign(rptr.begin(), rptr.end() - 1);
  for (I j = 0; j < m; ++j)
    for (I t = wptr[(size_t)j]; t < wptr[(size_t)j + 1]; ++t) {
      const I k = widx[(size_t)t], at = fill[(size_t)k]++;
      rcol[(size_t)at] = j, rval[(size_t)at] = W(k, j);
    }
  thread_local VectorXd g;
  thread_local std::vector<I> gptr, grow, hit;  // G's rows each column's sums reached (ascending); hit: last column
  g.setZero(m);
  if (scan) {  // every entry of MiW's column j, k ascending; every entry of G's column written
    for (I j = 0; j < m; ++j) {
      const double *y = MiW.col(j).data();
      for (I k = 0; k < nv; ++k) {
        const double ykj = y[k];
        if (ykj == 0.0) continue;
        for (I t = rptr[(size_t)k]; t < rptr[(size_t)k + 1]; ++t) {
          const I c = rcol[(size_t)t];
          g[c] = g[c] + rval[(size_t)t] * ykj;
        }
      }
      double *gj = G.col(j).data();
      for (I i = 0; i < m; ++i) gj[i] = g[i] + 0.0, g[i] = 0.0;
    }
    gi.set(G);
    kept = gi.finite, kept_at[0] = MiW.data(), kept_at[1] = G.data();
    return;
  }
  hit.assign((size_t)m, -1);
  gptr.assign((size_t)m + 1, 0), grow.clear();
  for (I j = 0; j < m; ++j) {  // G's column j: the sums over k ascending; the rows no term reaches stay +0.0
    const double *y = MiW.col(j).data();
    for (I t = mi.wptr[(size_t)j]; t < mi.wptr[(size_t)j + 1]; ++t) {  // MiW's nonzeros in column j, k ascending
      const I k = mi.widx[(size_t)t];
      const double ykj = y[k];
      if (ykj == 0.0) continue;
      for (I t = rptr[(size_t)k]; t < rptr[(size_t)k + 1]; ++t) {
        const I c = rcol[(size_t)t];
        g[c] = g[c] + rval[(size_t)t] * ykj;
        if (hit[(size_t)c] != j) hit[(size_t)c] = j, grow.push_back(c);
      }
    }
    gptr[(size_t)j + 1] = (I)grow.size();
    std::sort(grow.begin() + gptr[(size_t)j], grow.end());
    double *gj = G.col(j).data();
    for (I t = gptr[(size_t)j]; t < gptr[(size_t)j + 1]; ++t) {
      const I i = grow[(size_t)t];
      gj[i] = g[i] + 0.0, g[i] = 0.0;
    }
  }
  gi.set_listed(G, gptr, grow);
  // what the next call resets: mi's lists and G's nonzeros (G not finite: all of it, next time)
  kept = gi.finite, kept_at[0] = MiW.data(), kept_at[1] = G.data();
}

// otimes(A[:, cols], x) (A: MiW or W, cols ascending or not) as omatmul sums it, over the rows ai lists for each
// column (a superset of its nonzeros; the rows outside are +0.0) where ai.finite and x is finite: a term with a zero
// factor adds +-0 (contact_space's argument); else by omatmul on the columns copied
VectorXd otimes_cols(const MatrixXd &A, const WInfo &ai, const std::vector<Eigen::Index> &cols, const VectorXd &x) {
  const Eigen::Index nv = A.rows(), k = (Eigen::Index)cols.size();
  if (!ai.finite || !x.allFinite()) {
    MatrixXd Ac(nv, k);
    for (Eigen::Index i = 0; i < k; ++i) Ac.col(i) = A.col(cols[(size_t)i]);
    return otimes(Ac, x);
  }
  VectorXd y = VectorXd::Zero(nv);
  for (Eigen::Index c = 0; c < k; ++c) {
    const Eigen::Index j = cols[(size_t)c];
    const double *a = A.col(j).data(), xc = x[c];
    for (Eigen::Index t = ai.wptr[(size_t)j]; t < ai.wptr[(size_t)j + 1]; ++t) {
      const Eigen::Index i = ai.widx[(size_t)t];
      y[i] = y[i] + a[i] * xc;
    }
  }
  for (Eigen::Index i = 0; i < nv; ++i) y[i] = y[i] + 0.0;
  return y;
}

// otimes_t(W[:, cols], x) (sums.ordered(W[:, cols].T, x)): otimes_t_nz's sums on the columns cols
VectorXd otimes_t_cols(const MatrixXd &W, const WInfo &wi, const std::vector<Eigen::Index> &cols, const VectorXd &x) {
  const Eigen::Index k = (Eigen::Index)cols.size();
  VectorXd y(k);
  if (!wi.finite || !x.allFinite() || W.rows() == 0) {
    for (Eigen::Index c = 0; c < k; ++c) y[c] = W.rows() ? odot(W.col(cols[(size_t)c]).data(), x.data(), W.rows()) : 0.0;
    return y;
  }
  for (Eigen::Index c = 0; c < k; ++c) y[c] = wcol_dot(W, wi, cols[(size_t)c], x);
  return y;
}

// lu_solve(G[sel][:, sel], rhs, x) for project's final solves and the warm start's: where G is clean, sub_lu_solve
// on G_AA's nonzeros where G is sparse (GInfo::sparse) and sel has more than kSparseLU rows, else band_lu_solve (the
// same bits; on the active set's BandLU, band_cache); else lu_solve on the copy
bool solve_sub(const MatrixXd &G, const GInfo &gi, const std::vector<Eigen::Index> &sel, const VectorXd &rhs,
               VectorXd &x, bool fresh) {
  const Eigen::Index k = (Eigen::Index)sel.size();
  if (gi.is_clean) {
    if (schur_applies(gi, G.rows(), k)) return schur_solve(G, gi, sel, rhs, x, fresh);
    thread_local std::vector<Eigen::Index> pos;
    pos.assign((size_t)G.rows(), -1);
    for (Eigen::Index i = 0; i < k; ++i) pos[(size_t)sel[(size_t)i]] = i;
    if (gi.sparse && k > kSparseLU) return sub_lu_solve(gi, sel, pos.data(), rhs, x);
    return band_lu_solve(band_cache(), gi, sel, pos.data(), rhs, x);
  }
  MatrixXd GA(k, k);
  for (Eigen::Index i = 0; i < k; ++i)
    for (Eigen::Index j = 0; j < k; ++j) GA(i, j) = G(sel[(size_t)i], sel[(size_t)j]);
  return lu_solve(GA, rhs, x);
}

Solved project(const Constants &C, const MatrixXd &W, const VectorXd &v0, const VectorXd &b, const MatrixXd &Minv,
               const std::vector<char> *start = nullptr, const WInfo *given = nullptr, const Blocks *blocks = nullptr,
               bool start_any = false);

// islands.islands and qp._by_islands (docs/theory.md §1.3, islands): the rows (W's nonzeros by column, wi) fall into islands,
// the connected components of rows and the trees they touch (blocks: M's diagonal blocks by tree); each island is
// projected on its own trees' velocities (its own screen, tolerances and size rules, started from its rows of start at
// any size: start_any), the other velocities keep
// v0, act takes an island's first-pass set or, where it has none (one row, admissible), its rows with lam > 0 (as
// stepper.keep_active reads Python's). false where there is one island or a row touches no velocity (project takes the
// whole); an island project hands back throws Fallback, as Python then solves the whole (qp._by_islands: None)
bool by_islands(const Constants &C, const MatrixXd &W, const WInfo &wi, const VectorXd &v0, const VectorXd &b,
                const MatrixXd &Minv, const std::vector<char> *start, const Blocks &blocks, Solved &out) {
  using I = Eigen::Index;
  const I nv = W.rows(), m = W.cols(), nt = (I)blocks.size();
  std::vector<I> tree((size_t)nv, -1), parent((size_t)nt), first_tree((size_t)m);
  for (I t = 0; t < nt; ++t) {
    parent[(size_t)t] = t;
    for (I d = blocks[(size_t)t].first; d < blocks[(size_t)t].first + blocks[(size_t)t].second; ++d) tree[(size_t)d] = t;
  }
  auto root = [&](I t) {
    while (parent[(size_t)t] != t) t = parent[(size_t)t] = parent[(size_t)parent[(size_t)t]];
    return t;
  };
  for (I j = 0; j < m; ++j) {
    const I t0 = wi.wptr[(size_t)j], t1 = wi.wptr[(size_t)j + 1];
    if (t0 == t1) return false;
    first_tree[(size_t)j] = tree[(size_t)wi.widx[(size_t)t0]];
    for (I t = t0 + 1; t < t1; ++t) {
      const I a = root(first_tree[(size_t)j]), c = root(tree[(size_t)wi.widx[(size_t)t]]);
      if (a != c) parent[(size_t)std::max(a, c)] = std::min(a, c);
    }
  }
  std::vector<I> label((size_t)nt, -1), of_row((size_t)m);
  I n = 0;
  for (I j = 0; j < m; ++j) {
    const I r = root(first_tree[(size_t)j]);
    if (label[(size_t)r] < 0) label[(size_t)r] = n++;
    of_row[(size_t)j] = label[(size_t)r];
  }
  if (n < 2) return false;
  std::vector<std::vector<I>> dofs((size_t)n), rows((size_t)n);
  for (I t = 0; t < nt; ++t) {
    const I k = label[(size_t)root(t)];
    if (k >= 0)
      for (I d = blocks[(size_t)t].first; d < blocks[(size_t)t].first + blocks[(size_t)t].second; ++d)
        dofs[(size_t)k].push_back(d);
  }
  for (I j = 0; j < m; ++j) rows[(size_t)of_row[(size_t)j]].push_back(j);
  out = Solved{v0, VectorXd::Zero(m), Projection::ADMISSIBLE, std::vector<char>((size_t)m, 0)};
  for (I k = 0; k < n; ++k) {
    const auto &D = dofs[(size_t)k], &R = rows[(size_t)k];
    const I nd = (I)D.size(), nr = (I)R.size();
    MatrixXd Wk(nd, nr), Mk(nd, nd);
    VectorXd vk(nd), bk(nr);
    for (I c = 0; c < nr; ++c)
      for (I i = 0; i < nd; ++i) Wk(i, c) = W(D[(size_t)i], R[(size_t)c]);
    for (I c = 0; c < nd; ++c)
      for (I i = 0; i < nd; ++i) Mk(i, c) = Minv(D[(size_t)i], D[(size_t)c]);
    for (I i = 0; i < nd; ++i) vk[i] = v0[D[(size_t)i]];
    for (I c = 0; c < nr; ++c) bk[c] = b[R[(size_t)c]];
    std::vector<char> sk;
    if (start)
      for (I c = 0; c < nr; ++c) sk.push_back((*start)[(size_t)R[(size_t)c]]);
    const Solved s = project(C, Wk, vk, bk, Mk, start ? &sk : nullptr, nullptr, nullptr, true);
    for (I i = 0; i < nd; ++i) out.v[D[(size_t)i]] = s.v[i];
    for (I c = 0; c < nr; ++c) {
      out.lam[R[(size_t)c]] = s.lam[c];
      out.act[(size_t)R[(size_t)c]] = (I)s.act.size() == nr ? s.act[(size_t)c] : (char)(s.lam[c] > 0.0);
    }
    if (s.status != Projection::ADMISSIBLE) out.status = s.status;
  }
  return true;
}

// qp.solve (primal form, Polish.ACTIVE_SET): the screen, the closed form for one row, else qp._polish: the active
// set (from nothing, or above qp.SPARSE_ROWS rows from `start`: qp.solve's start, the previous step's final set),
// re-solved on its final set and checked. Throws Fallback where qp.solve would go on to piqp. G's and W's nonzeros are found once (GInfo, WInfo) and each product W'v is
// formed once (W'v0 for the screen and r; W'vp for r2 and the last check, or W'v2 where the second pass is kept).
Solved project(const Constants &C, const MatrixXd &W, const VectorXd &v0, const VectorXd &b, const MatrixXd &Minv,
               const std::vector<char> *start, const WInfo *given, const Blocks *blocks, bool start_any) {
  const Eigen::Index m = W.cols(), nv = W.rows();
  // qp.solve's NON_FINITE_INPUT: the Python step takes it and stops the run naming the step (an overflow upstream)
  if (!v0.allFinite()) throw Fallback{"a non-finite velocity to project"};
  thread_local WInfo own;
  if (!given) own.set(W);
  const WInfo &wi = given ? *given : own;  // given: the caller's WInfo of this W
  VectorXd Wv0;
  otimes_t_nz(W, wi, v0, Wv0);
  const VectorXd slack0 = Wv0 - b;
  if (slack0.minCoeff() >= -C.screen * (1.0 + v0.cwiseAbs().maxCoeff())) return {v0, VectorXd::Zero(m), Projection::ADMISSIBLE};
  if (m == 1) {
    const VectorXd w = W.col(0);
    const VectorXd Miw = otimes(Minv, w);
    const double lam1 = std::max(0.0, (b[0] - odot(w.data(), v0.data(), nv)) / odot(w.data(), Miw.data(), nv));
    VectorXd v = v0 + lam1 * Miw;
    return {v, VectorXd::Constant(1, lam1), Projection::ACTIVE_SET};
  }
  if (blocks && m > C.sparse_rows && wi.finite) {  // qp.solve's islands (above qp.SPARSE_ROWS rows)
    Solved split;
    if (by_islands(C, W, wi, v0, b, Minv, start, *blocks, split)) return split;
  }
  if ((m <= C.sparse_rows && !start_any) || (start && std::find(start->begin(), start->end(), 1) == start->end()))
    start = nullptr;
  // above qp.WARM_ROWS rows a projection without a start goes to qp.solve's sparse path (piqp + SuperLU's start)
  if (m > C.warm_rows && !start) throw Fallback{"more rows than the active set takes from nothing"};
  const double scale = 1.0 + v0.cwiseAbs().maxCoeff();
  // Minv @ W, W.T @ MiW: kept from one call to the next (no fresh O(nv m) allocation; every entry written by
  // contact_space); project is never re-entered while its MiW, G are in use
  thread_local MatrixXd MiW, G;
  thread_local WInfo mi;  // MiW's columns' rows (contact_space)
  thread_local GInfo gi;  // G's nonzeros (contact_space)
  contact_space(Minv, W, wi, MiW, G, mi, gi, blocks);
  const VectorXd r = b - Wv0;
  // qp._polish, from the active set on (schur.retried: where it has no answer after solves by the complement, once
  // more with direct factors alone)
  auto polish = [&]() -> Solved {
    std::vector<char> act;
    VectorXd lam;
    if (!active_set(C, G, gi, r, C.screen * scale, act, lam, start)) throw Fallback{"active set did not settle"};
    std::vector<Eigen::Index> idx;
    for (Eigen::Index i = 0; i < m; ++i)
      if (act[i]) idx.push_back(i);
    const Eigen::Index k = (Eigen::Index)idx.size();
    VectorXd lp = VectorXd::Zero(m), vp;
    VectorXd Wvp;  // W'vp for the last check
    if (!k) {
      vp = v0;
      Wvp = Wv0;
    } else {
      VectorXd rA(k), lamA;
      for (Eigen::Index i = 0; i < k; ++i) rA[i] = r[idx[i]];
      if (!solve_sub(G, gi, idx, rA, lamA, true) || lamA.minCoeff() < -C.accept * std::max(1.0, lamA.maxCoeff()))
        throw Fallback{"active set's final solve rejected"};
      for (Eigen::Index i = 0; i < k; ++i) lamA[i] = std::max(lamA[i], 0.0);
      vp = v0 + otimes_cols(MiW, mi, idx, lamA);
      // qp._polish's refinement step: the residual of W_P'v = b_P solved for on the rows that push
      std::vector<Eigen::Index> pi, iP;
      for (Eigen::Index i = 0; i < k; ++i)
        if (lamA[i] > 0.0) pi.push_back(i), iP.push_back(idx[i]);
      const Eigen::Index kp = (Eigen::Index)iP.size();
      if (kp) {
        const VectorXd WPv = otimes_t_cols(W, wi, iP, vp);
        VectorXd rP(kp), dP;
        for (Eigen::Index i = 0; i < kp; ++i) rP[i] = b[iP[i]] - WPv[i];
        if (solve_sub(G, gi, iP, rP, dP) && dP.cwiseAbs().maxCoeff() <= C.refine * (1.0 + lamA.maxCoeff())) {
          for (Eigen::Index i = 0; i < kp; ++i) lamA[pi[i]] = std::max(lamA[pi[i]] + dP[i], 0.0);
          vp = vp + otimes_cols(MiW, mi, iP, dP);
        }
      }
      for (Eigen::Index i = 0; i < k; ++i) lp[idx[i]] = lamA[i];
      // qp._polish's second pass: the active set on the answer's own residual
      otimes_t_nz(W, wi, vp, Wvp);
      const VectorXd r2 = b - Wvp;
      const double tol2 = C.second_pass * (b.cwiseAbs().maxCoeff() + wi.abs_max(W) * vp.cwiseAbs().maxCoeff());
      std::vector<char> act2;
      VectorXd dl;
      if (active_set(C, G, gi, r2, tol2, act2, dl)) {
        std::vector<Eigen::Index> i2;
        for (Eigen::Index i = 0; i < m; ++i)
          if (act2[i]) i2.push_back(i);
        const Eigen::Index k2 = (Eigen::Index)i2.size();
        if (k2) {
          VectorXd d2(k2);
          for (Eigen::Index i = 0; i < k2; ++i) d2[i] = dl[i2[i]];
          const VectorXd v2 = vp + otimes_cols(MiW, mi, i2, d2);
          VectorXd Wv2;
          otimes_t_nz(W, wi, v2, Wv2);
          if ((Wv2 - b).minCoeff() >= -r2.maxCoeff()) {
            vp = v2;
            Wvp = std::move(Wv2);
            for (Eigen::Index i = 0; i < k2; ++i) lp[i2[i]] = lp[i2[i]] + d2[i];
          }
        }
      }
    }
    if ((Wvp - b).minCoeff() < -C.accept * scale) throw Fallback{"active set's answer rejected"};
    return {vp, lp, Projection::ACTIVE_SET, std::move(act)};
  };
  schur_state().used = false;
  try {
    return polish();
  } catch (const Fallback &) {
    if (!schur_state().used) throw;
    schur_state().off = true;
    try {
      Solved s = polish();
      schur_state().off = false;
      return s;
    } catch (...) {
      schur_state().off = false;
      throw;
    }
  }
}

}  // namespace

// coal's cached GJK guesses of a list of queries' requests and results: saved before a step, put back where it is
// undone (run.cpp's Runner: the distance queries; Stepper::save_guesses keeps the collision queries' own)
struct QueryGuesses {
  std::vector<std::pair<coal::Vec3s, coal::support_func_guess_t>> req, res;
  template <class Rq, class Rs> void save(const std::vector<Rq> &rqs, const std::vector<Rs> &rss) {
    const size_t n = rqs.size();
    req.resize(n), res.resize(n);
    for (size_t k = 0; k < n; ++k) {
      req[k] = {rqs[k].cached_gjk_guess, rqs[k].cached_support_func_guess};
      res[k] = {rss[k].cached_gjk_guess, rss[k].cached_support_func_guess};
    }
  }
  template <class Rq, class Rs> void restore(std::vector<Rq> &rqs, std::vector<Rs> &rss) const {
    for (size_t k = 0; k < req.size() && k < rqs.size(); ++k) {
      rqs[k].cached_gjk_guess = req[k].first, rqs[k].cached_support_func_guess = req[k].second;
      rss[k].cached_gjk_guess = res[k].first, rss[k].cached_support_func_guess = res[k].second;
    }
  }
};

// constraints.distinct: the columns of W kept, those whose row repeats no earlier one (max |w_i - w_j| <= rel (1 + max|W|));
// Stepper::distinct, bound as _step.distinct_rows for the tests
std::vector<int> distinct_rows(const MatrixXd &W, double rel, const WInfo *given = nullptr) {
  const Eigen::Index m = W.cols();
  std::vector<int> keep;
  if (m < 2) {
    for (int i = 0; i < m; ++i) keep.push_back(i);
    return keep;
  }
  // W's nonzeros by columns (given: the caller's, contact_rows'), ascending
  thread_local WInfo own;
  if (!given) own.set(W);
  const WInfo &wi = given ? *given : own;
  const double thr = rel * (1.0 + wi.abs_max(W));
  const Eigen::Index nv = W.rows();
  // W finite: max|w_i - w_j| <= thr is every |w_vi - w_vj| <= thr, compared where either row is nonzero (from
  // the first nonzero entry of either to the last), the first that is not ending the comparison
  const bool finite = wi.finite;
  std::vector<Eigen::Index> lo((size_t)m, nv), hi((size_t)m, 0);
  for (Eigen::Index j = 0; j < m && finite; ++j)
    if (wi.wptr[(size_t)j + 1] > wi.wptr[(size_t)j])
      lo[(size_t)j] = wi.widx[(size_t)wi.wptr[(size_t)j]], hi[(size_t)j] = wi.widx[(size_t)wi.wptr[(size_t)j + 1] - 1] + 1;
  auto same = [&](Eigen::Index i, Eigen::Index j) {
    if (!finite) return (W.col(i) - W.col(j)).cwiseAbs().maxCoeff() <= thr;
    const double *a = W.col(i).data(), *b = W.col(j).data();
    Eigen::Index v = std::min(lo[(size_t)i], lo[(size_t)j]);
    const Eigen::Index end = std::max(hi[(size_t)i], hi[(size_t)j]);
    while (v < end && std::abs(a[v] - b[v]) <= thr) ++v;
    return v >= end;
  };
  // W finite: a row i repeating row j (i < j) is within thr of it at s_j, row j's largest |entry| (the first), and so
  // nonzero there where |w_j| > thr at s_j; and fl(x - y) never decreases as x grows, so the rows whose entry x at
  // s_j passes |fl(x - y)| <= thr (y: row j's) are an interval of the entries at s_j sorted by value: found by binary
  // search and compared in full (same). A row within thr of 0 everywhere is compared with every row before it.
  // Whether any earlier row repeats row j is all that counts: the same keep, at a few rows a row, not m.
  std::vector<Eigen::Index> top((size_t)m, 0), ptr(finite ? (size_t)nv + 1 : 0, 0);
  std::vector<std::pair<double, Eigen::Index>> ent;  // each velocity's nonzero entries (value, row), by value
  if (finite) {
    for (Eigen::Index j = 0; j < m; ++j) {  // over the nonzeros, ascending: the first largest |entry|, as a scan
      const double *w = W.col(j).data();
      for (Eigen::Index t = wi.wptr[(size_t)j]; t < wi.wptr[(size_t)j + 1]; ++t) {
        const Eigen::Index v = wi.widx[(size_t)t];
        ++ptr[(size_t)v + 1];
        if (std::abs(w[v]) > std::abs(w[top[(size_t)j]])) top[(size_t)j] = v;
      }
    }
    for (Eigen::Index v = 0; v < nv; ++v) ptr[(size_t)v + 1] += ptr[(size_t)v];
    ent.resize((size_t)ptr[(size_t)nv]);
    std::vector<Eigen::Index> put(ptr.begin(), ptr.end() - 1);
    for (Eigen::Index j = 0; j < m; ++j)
      for (Eigen::Index t = wi.wptr[(size_t)j]; t < wi.wptr[(size_t)j + 1]; ++t) {
        const Eigen::Index v = wi.widx[(size_t)t];
        ent[(size_t)put[(size_t)v]++] = {W(v, j), j};
      }
    for (Eigen::Index v = 0; v < nv; ++v) std::sort(ent.begin() + ptr[(size_t)v], ent.begin() + ptr[(size_t)v + 1]);
  }
  for (Eigen::Index j = 0; j < m; ++j) {
    bool dup = false;
    const Eigen::Index sj = top[(size_t)j];
    const double y = finite ? W(sj, j) : 0.0;
    if (!finite || !(std::abs(y) > thr)) {
      for (Eigen::Index i = 0; i < j && !dup; ++i) dup = same(i, j);
    } else {
      const auto b = ent.begin() + ptr[(size_t)sj], e = ent.begin() + ptr[(size_t)sj + 1];
      auto it = std::partition_point(b, e, [&](const std::pair<double, Eigen::Index> &x) { return x.first - y < -thr; });
      for (; it != e && it->first - y <= thr && !dup; ++it)
        if (it->second < j) dup = same(it->second, j);
    }
    if (!dup) keep.push_back((int)j);
  }
  return keep;
}

#include "forest.hpp"  // the per-tree models and Datas the Stepper computes on (docs/theory.md §2.12)

class Stepper {
  friend class Runner;  // the run loop (src/run.cpp) calls the step and reads its model and geometry
  friend class ForestFigures;  // the figures a sample records (src/run.cpp) read its geometry
  friend class EventImpact;  // the impact at a located event (src/impact.hpp) calls the detection, rows and projection

 public:
  // model: the scene's pin.Model (its joint maps; pin.integrate, which takes no Data); trees, tree_of_joint,
  // local_joint: the forest the dynamics and kinematics run on (Forest, compiled.forest_args): no whole-model Data
  Stepper(nb::object model, const Forest::TreeArgs &trees, std::vector<int64_t> tree_of_joint,
          std::vector<int64_t> local_joint, nb::object geom_model, nb::object geom_data,
          std::vector<MatrixXd> vertices, std::vector<int> bound_kind, std::vector<Vec3> bound_a,
          std::vector<double> bound_b, Eigen::Matrix<int64_t, Eigen::Dynamic, Eigen::Dynamic> pairs,
          double reach, double thinnest_pair, double tol, int tunnelling, bool separating_elastic,
          bool slow_plastic, bool bias_midpoint, bool velocity_bias, bool projection,
          const std::map<std::string, double> &constants, MatrixXd limits)
      : py_{model, geom_model, geom_data},
        model_(extract_ref<pinocchio::Model>(model, "pinocchio.Model")),
        forest_(trees, std::move(tree_of_joint), std::move(local_joint)),
        gm_(extract_ref<pinocchio::GeometryModel>(geom_model, "pinocchio.GeometryModel")),
        gd_(extract_ref<pinocchio::GeometryData>(geom_data, "pinocchio.GeometryData")),
        vertices_(std::move(vertices)), bound_kind_(std::move(bound_kind)), bound_a_(std::move(bound_a)),
        bound_b_(std::move(bound_b)), pairs_(std::move(pairs)), reach_(reach),
        thinnest_(thinnest_pair), tol_(tol), tunnelling_(tunnelling), sep_elastic_(separating_elastic),
        slow_plastic_(slow_plastic), bias_midpoint_(bias_midpoint), velocity_bias_(velocity_bias),
        projection_(projection), C_(Constants::from(constants)),
        limits_(std::move(limits)) {
    if (pairs_.cols() != 5 || (Eigen::Index)gm_.collisionPairs.size() != pairs_.rows())
      throw nb::value_error("pairs: (number of collision pairs, 5) expected");
    support_.resize((size_t)model_.njoints);
    for (int j = 1; j < model_.njoints; ++j) {
      for (size_t k = 1; k < model_.supports[(size_t)j].size(); ++k) {
        const auto &jm = model_.joints[(size_t)model_.supports[(size_t)j][k]];
        for (int v = 0; v < jm.nv(); ++v) support_[(size_t)j].push_back((Eigen::Index)(jm.idx_v() + v));
      }
      std::sort(support_[(size_t)j].begin(), support_[(size_t)j].end());
    }
    if (forest_.nq() != model_.nq || forest_.nv() != model_.nv || (int)forest_.njoints() != model_.njoints)
      throw nb::value_error("trees: the forest of the model (nq, nv, a map entry per joint) expected");
    for (const auto &tr : forest_.trees()) blocks_.emplace_back((Eigen::Index)tr.v0, (Eigen::Index)tr.nv);
    if (limits_.cols() != 6) throw nb::value_error("limits: (number of joint limits, 6) expected");
  }

  StepOut step(const VectorXd &q, const VectorXd &u, double h, double e, const VectorXd &tau, double t) {
    StepOut out;
    out.spare = spare_;
    if (tau.size() != 0 && tau.size() != model_.nv) throw nb::value_error("tau: size nv (or empty) expected");
    if ((rh_.driven() || !rh_.moving.empty()) && !std::isfinite(t))
      throw nb::value_error("t: the step's start time is needed (a moving static or a driven joint)");
    tau_ = tau;  // the step's joint torques (actuation.py), evaluated by Python at (t_m, q_m, u_k); empty: none
    try {
      next_active_.clear();  // step_ fills it where its projection has more than C_.sparse_rows rows
      step_(q, u, h, e, t, out);
      warm_.swap(next_warm_);  // the pairs with contacts at this detection (contacts.detect's warm start)
      active_.swap(next_active_);  // the projection's warm start (stepper.keep_active)
    } catch (const Fallback &f) {
      restore_guesses();
      out = StepOut();
      out.spare = spare_;
      out.outcome = Outcome::FALLBACK, out.reason = f.why;
    }
    return out;
  }

  std::map<std::string, double> constants() const { return C_.as_dict(); }

  // The detection's data beyond coal's narrow phase (moreau_sim/compiled.py _Context._shapes): per geometry, its point
  // query (data.point_query, the same coal functor Python calls; None: no vertex is queried against it), its face
  // normals (k, 3), face planes (a box's: normals (6, 3), offsets; none: (0, 3)), edges (a box's box_box.box_edges:
  // starts, directions, lengths, the two face normals, (12, 13); none: (0, 13)) in its joint frame, the edges
  // leaving each of its vertices (model.vertex_edges: (vertices cone, 3)) and cone, their number per vertex (-1:
  // unknown, None in Python); per pair whether both are polytopes (model.polytope_pair_set); the coal request and
  // result objects Python's detection uses (data.distance_request, data.distance_result, data.patch_request);
  // carries: whether the detection carries state from one step to the next (coal's GJK warm starts, the near pairs
  // of two polytopes), which a step handed back or undone restores
  void boxes(std::vector<nb::object> queries, std::vector<MatrixXd> face_normals, std::vector<MatrixXd> plane_n,
             std::vector<VectorXd> plane_d, std::vector<MatrixXd> edges, std::vector<MatrixXd> vertex_edges,
             std::vector<int> cone, std::vector<int> polytope, nb::object dreq, nb::object dres, nb::object preq,
             bool carries) {
    const size_t G = gm_.geometryObjects.size();
    if (queries.size() != G || face_normals.size() != G || plane_n.size() != G || plane_d.size() != G ||
        edges.size() != G || vertex_edges.size() != G || cone.size() != G ||
        (Eigen::Index)polytope.size() != pairs_.rows())
      throw nb::value_error("boxes: one entry per geometry (per pair: polytope) expected");
    keep_.assign({dreq, dres, preq});
    dreq_ = &extract_ref<coal::DistanceRequest>(dreq, "coal.DistanceRequest");
    dres_ = &extract_ref<coal::DistanceResult>(dres, "coal.DistanceResult");
    preq_ = &extract_ref<coal::ContactPatchRequest>(preq, "coal.ContactPatchRequest");
    query_.assign(G, nullptr), face_n_.resize(G), plane_n_.resize(G), plane_d_ = std::move(plane_d), edges_.resize(G);
    half_.assign(G, Vec3::Zero()), vedges_.resize(G), is_box_.assign(G, 0), cone_ = std::move(cone);
    for (size_t g = 0; g < G; ++g) {
      if (!queries[g].is_none()) {
        keep_.push_back(queries[g]);
        query_[g] = &extract_ref<coal::ComputeDistance>(queries[g], "coal.ComputeDistance");
      }
      if (plane_n[g].cols() != 3 || plane_d_[g].size() != plane_n[g].rows())
        throw nb::value_error("boxes: face planes (k, 3), (k,) per geometry");
      if (cone_[g] >= 0 && vertex_edges[g].rows() != vertices_[g].rows() * cone_[g])
        throw nb::value_error("boxes: vertex edges (vertices cone, 3) per geometry");
      vedges_[g] = vertex_edges[g];
      if (edges[g].rows()) {
        if (edges[g].rows() != 12 || edges[g].cols() != 13 ||
            gm_.geometryObjects[g].geometry->getNodeType() != coal::GEOM_BOX)
          throw nb::value_error("boxes: edges (12, 13) per box, none for any other shape");
        is_box_[g] = 1;
        boxbox::Edges &E = edges_[g];
        E.e0 = edges[g].leftCols(3), E.ed = edges[g].middleCols(3, 3), E.el = edges[g].col(6);
        E.f0 = edges[g].middleCols(7, 3), E.f1 = edges[g].rightCols(3);
        half_[g] = static_cast<const coal::Box *>(gm_.geometryObjects[g].geometry.get())->halfSide;
      }
      face_n_[g] = face_normals[g], plane_n_[g] = plane_n[g];
    }
    polytope_.assign(polytope.begin(), polytope.end());
    shapes_ = true, boxes_ = carries;
  }
  // The detection's broad phase (moreau_sim/broad_phase.py BroadPhase, the same data): per geometry its joint, the
  // centre and half extents of its box in the joint frame, whether it is bounded; the margin [m]; the pairs of a
  // half-space {n.x <= d} (pair, half-space, other; n, d in the half-space's joint frame); the pairs always examined
  void broad(std::vector<int> joint, MatrixXd centre, MatrixXd half, std::vector<int> bounded, double margin,
             std::vector<int> half_pair, std::vector<int> half_geom, std::vector<int> half_other, MatrixXd half_n,
             VectorXd half_d, std::vector<int> always) {
    const size_t G = gm_.geometryObjects.size(), H = half_pair.size();
    if (joint.size() != G || (size_t)centre.rows() != G || (size_t)half.rows() != G || centre.cols() != 3 ||
        half.cols() != 3 || half_geom.size() != H || half_other.size() != H || (size_t)half_n.rows() != H ||
        (size_t)half_d.size() != H)
      throw nb::value_error("broad: one entry per geometry (per half-space pair) expected");
    bp_ = BroadPhase{std::move(joint), std::move(centre), std::move(half), std::move(bounded), margin,
                     std::move(half_pair), std::move(half_geom), std::move(half_other), std::move(half_n),
                     std::move(half_d), std::move(always), {}};
    const int64_t nG = (int64_t)G;
    for (Eigen::Index k = 0; k < pairs_.rows(); ++k)
      bp_->index[std::min(pairs_(k, 0), pairs_(k, 1)) * nG + std::max(pairs_(k, 0), pairs_(k, 1))] = (int)k;
  }
  // The model's moving statics (prescribed.Prescribed.moving: (geometry, base rotation, base translation, schedule))
  // and driven joints (drive.Drive: (velocity row, schedule) in increasing rows), the schedules as
  // compiled.schedule hands them over (docs/theory.md §2.9, §2.13)
  void rheonomic(std::vector<std::tuple<int64_t, Eigen::Matrix3d, Vec3, nb::object>> moving,
                 std::vector<std::pair<int64_t, nb::object>> driven) {
    rheonomic::Model rh;
    rh.moving_of.assign(gm_.geometryObjects.size(), -1);
    for (auto &[g, R, p, sc] : moving) {
      if (g < 0 || (size_t)g >= gm_.geometryObjects.size() || gm_.geometryObjects[(size_t)g].parentJoint != 0)
        throw nb::value_error("rheonomic: a moving geometry must be a static");
      rheonomic::Moving m;
      m.geometry = (size_t)g, m.base = pinocchio::SE3(R, p), m.schedule = rheonomic::Schedule::from(sc);
      if (m.schedule.n != 3) throw nb::value_error("rheonomic: a moving static's schedule has 3 components");
      rh.moving_of[(size_t)g] = (int)rh.moving.size();
      rh.moving.push_back(std::move(m));
    }
    std::vector<char> is_d(model_.nv, 0);
    for (auto &[v, sc] : driven) {
      if (v < 0 || v >= model_.nv || is_d[v] || (!rh.d.empty() && v < rh.d.back()))
        throw nb::value_error("rheonomic: driven rows increasing, within nv");
      is_d[v] = 1, rh.d.push_back(v), rh.drives.push_back(rheonomic::Schedule::from(sc));
      if (rh.drives.back().n != 1) throw nb::value_error("rheonomic: a drive's schedule has 1 component");
    }
    for (Eigen::Index v = 0; v < model_.nv; ++v)
      if (!is_d[v]) rh.r.push_back(v);
    rh_ = std::move(rh);
  }
  // contacts.detect's warm start (data.warm_start_pairs): set before a step, read after it
  std::vector<int> warm() const { return warm_; }
  // the broad phase's candidates at the last detection (broad())
  std::vector<int> last_candidates() const { return cand_; }
  void set_warm(std::vector<int> w) { warm_ = std::move(w); }
  // The pairs of a scene without their list (moreau_sim/pair_table.py PairTable, the same arrays; src/pair_table.hpp):
  // the Stepper then holds no pair list (its GeometryModel has the geometries and no pair) and queries coal on the
  // broad phase's candidates through the objects Python's Data makes per pair at first use: collide_query(k) ->
  // (CollisionRequest, CollisionResult, ComputeCollision) (data.Data.pair_query), distance_query(k) ->
  // (DistanceRequest, DistanceResult, ComputeDistance) (data.Data.distance_query), shared with the Python step
  void table(int64_t G, std::vector<int64_t> joint, std::vector<int64_t> removed, std::vector<int64_t> start,
             std::vector<int> half, std::vector<int> poly, std::vector<int> flat, std::vector<int> faces,
             nb::object collide_query, nb::object distance_query) {
    const size_t n = (size_t)G;
    if (G != (int64_t)gm_.geometryObjects.size() || joint.size() != n || start.size() != n + 1 || half.size() != n ||
        poly.size() != n || flat.size() != n || faces.size() != n || pairs_.rows() != 0)
      throw nb::value_error("table: one entry per geometry (start: G + 1), and no pair list");
    if (!std::is_sorted(removed.begin(), removed.end())) throw nb::value_error("table: removed keys sorted");
    const auto flags = [](const std::vector<int> &x) { return std::vector<char>(x.begin(), x.end()); };
    table_ = pairs::Table{G, std::move(joint), std::move(removed), std::move(start), flags(half), flags(poly),
                          flags(flat), flags(faces)};
    collide_query_ = std::move(collide_query), distance_query_ = std::move(distance_query);
    cq_.clear(), dq_.clear(), query_keep_.clear();
  }
  // the records' reach [m] (Model.gap_reach) and the broad phase's margin for it (broad_phase.within's): a scene
  // without a pair list records its gaps per geometry (geometry_gaps below)
  void gap_reach(double reach, double margin) { gap_reach_ = reach, gap_margin_ = margin, gaps_per_geometry_ = true; }
  // contacts.geometry_gaps at q (for the tests; the run loop writes into its sample's row)
  VectorXd geometry_gaps_at(const VectorXd &q) {
    if (!gaps_per_geometry_ || !bp_) throw nb::value_error("geometry_gaps: gap_reach() first, on a broad phase");
    VectorXd out(gm_.geometryObjects.size());
    geometry_gaps(q, out.data());
    return out;
  }
  // the projection's warm start (data.active_rows: the (pair, kind, feature) of the rows that pushed in the last
  // step's projection above qp.SPARSE_ROWS rows, sorted): set before a step, read after it
  std::vector<std::array<int64_t, 3>> active() const { return active_; }
  void set_active(std::vector<std::array<int64_t, 3>> a) {
    std::sort(a.begin(), a.end());
    active_ = std::move(a);
  }

 private:
  nb::object py_[3];  // keeps the Python objects (and so the C++ ones) alive
  VectorXd tau_;  // the current step's joint torques (empty: none)
  const pinocchio::Model &model_;  // the scene's (no Data of it: its joints' maps and pin.integrate)
  Forest forest_;  // the dynamics and kinematics, per tree (docs/theory.md §2.12)
  Blocks blocks_;  // (first velocity, nv) of each tree: M's and M^-1's blocks
  std::shared_ptr<Spare> spare_ = std::make_shared<Spare>();  // the StepOuts' M and W, handed back (Spare)
  MatrixXd M_, Minv_, J_;  // M and M^-1 (nv, nv, block diagonal: made at first use), the WORLD Jacobians (6, nv)
  const pinocchio::GeometryModel &gm_;
  pinocchio::GeometryData &gd_;
  std::vector<MatrixXd> vertices_;
  std::vector<int> bound_kind_;  // 0: half-space {n.x <= d} ("plane"), 1: bounding sphere
  std::vector<Vec3> bound_a_;
  std::vector<double> bound_b_;
  Eigen::Matrix<int64_t, Eigen::Dynamic, Eigen::Dynamic> pairs_;  // first, second, joint_first, joint_second, patch
  // the velocities that move each joint (model.support_mask's ones: the joints of model.supports[j] but the
  // universe), ascending
  std::vector<std::vector<Eigen::Index>> support_;
  double reach_, thinnest_, tol_;
  int tunnelling_;  // 0 swept, 1 none, 2 always
  bool sep_elastic_, slow_plastic_, bias_midpoint_, velocity_bias_, projection_;
  Constants C_;
  MatrixXd limits_;  // model.limits: pair, joint, idx_q, idx_v, sign, bound per limit (moreau_sim/limits.py)
  rheonomic::Model rh_;  // the moving statics and driven joints (rheonomic())
  // the detection's data beyond the narrow phase (boxes()): set (shapes_); carrying state between steps (boxes_: the
  // run loop's Undo restores it, src/run.cpp)
  bool shapes_ = false, boxes_ = false;
  std::vector<char> is_box_;  // a box (its edges in edges_)
  std::vector<int> cone_;  // edges per vertex in vedges_ (-1: unknown)
  struct BroadPhase {  // broad(): moreau_sim/broad_phase.py's data
    std::vector<int> joint;
    MatrixXd centre, half;
    std::vector<int> bounded;
    double margin;
    std::vector<int> half_pair, half_geom, half_other;
    MatrixXd half_n;
    VectorXd half_d;
    std::vector<int> always;
    std::unordered_map<int64_t, int> index;  // min(i, j) G + max(i, j) -> the pair of geometries i, j
  };
  std::optional<BroadPhase> bp_;
  std::optional<pairs::Table> table_;  // table(): the pairs of a scene without their list (pairs_ then has no row)
  struct CollisionQuery {  // a pair's coal collision objects: the GeometryData's, or Python's (table mode)
    coal::CollisionRequest *req;
    coal::CollisionResult *res;
    coal::ComputeCollision *f;
  };
  struct DistanceQuery {  // a pair's coal distance objects (table mode: Python's)
    coal::DistanceRequest *req;
    coal::DistanceResult *res;
    coal::ComputeDistance *f;
  };
  nb::object collide_query_, distance_query_;
  std::unordered_map<int, CollisionQuery> cq_;
  std::unordered_map<int, DistanceQuery> dq_;
  std::vector<nb::object> query_keep_;  // the Python objects behind cq_ and dq_
  std::vector<int> cand_;  // the broad phase's candidates at the last detection (sorted)
  std::vector<int> gap_cand_;  // scratch: geometry_gaps' candidates
  double gap_reach_ = 0.0, gap_margin_ = 0.0;  // gap_reach()
  bool gaps_per_geometry_ = false;  // gap_reach() was called: the samples' gaps are per geometry
  bool journal_on_ = false;  // journal_begin()
  struct SavedDistance {  // a distance query's guesses (request, result): journal_distance
    coal::Vec3s req;
    coal::support_func_guess_t req_hint;
    coal::Vec3s res;
    coal::support_func_guess_t res_hint;
  };
  std::unordered_map<int, SavedDistance> journal_;
  MatrixXd bp_c_, bp_h_;  // scratch: the geometries' boxes in the world
  std::vector<nb::object> keep_;
  coal::DistanceRequest *dreq_ = nullptr;
  coal::DistanceResult *dres_ = nullptr;
  coal::ContactPatchRequest *preq_ = nullptr;
  std::vector<coal::ComputeDistance *> query_;
  std::vector<boxbox::RowsX3> face_n_, plane_n_, vedges_;
  std::vector<VectorXd> plane_d_;
  std::vector<boxbox::Edges> edges_;
  std::vector<Vec3> half_;  // a box's half sides
  std::vector<char> polytope_;
  std::vector<int> warm_, next_warm_;  // sorted pair indices
  std::vector<std::array<int64_t, 3>> active_, next_active_;  // sorted (pair, kind, feature): stepper.warm_start
  coal::DistanceResult saved_dres_;

  // ---- Pinocchio's algorithms on the forest (trees.Forest, src/forest.hpp), as the Python bindings return them
  // (crba and Minv symmetrized): M (nv, nv) block diagonal, and the WORLD Jacobians J_ (Forest.mass_matrix)
  const MatrixXd &crba_world(const VectorXd &q) {
    if (M_.rows() != model_.nv) M_.setZero(model_.nv, model_.nv);  // the blocks off the trees stay zero
    if (J_.cols() != model_.nv) J_.setZero(6, model_.nv);
    forest_.mass_matrix(q, M_, J_);
    return M_;
  }
  const MatrixXd &minverse(const VectorXd &q) {  // Forest.inverse_mass_matrix
    if (Minv_.rows() != model_.nv) Minv_.setZero(model_.nv, model_.nv);
    forest_.inverse_mass_matrix(q, Minv_);
    return Minv_;
  }
  // Forest.acceleration: M^-1 (tau - h(q, v)) by ABA per tree
  VectorXd aba(const VectorXd &q, const VectorXd &v, const VectorXd &tau) { return forest_.acceleration(q, v, tau); }
  double kinetic(const VectorXd &q, const VectorXd &u) { return forest_.kinetic(q, u); }  // energy.kinetic
  double potential(const VectorXd &q) { return forest_.potential(q); }  // energy.potential
  double energy(const VectorXd &q, const VectorXd &u) {
    double T = kinetic(q, u);
    double V = potential(q);
    return T + V;
  }
  // Forest.place with the geometries' placements (pin.updateGeometryPlacements on the forest)
  void place_geometries(const VectorXd &q) { forest_.place(q, gm_, gd_); }
  // contacts.pair_distances into out (one per pair): NaN where coal's query failed (its -DBL_MAX is no distance)
  void distances(const VectorXd &q, double *out) {
    fresh_guesses(gd_.distanceRequests);
    place_geometries(q);
    pinocchio::computeDistances(gm_, gd_);
    for (size_t k = 0; k < gd_.distanceResults.size(); ++k) {
      const double x = gd_.distanceResults[k].min_distance;
      out[k] = std::abs(x) < C_.distance_failed ? x : std::numeric_limits<double>::quiet_NaN();
    }
  }
  VectorXd pair_distances(const VectorXd &q) {
    VectorXd d(gd_.distanceResults.size());
    distances(q, d.data());
    return d;
  }
  // contacts.pair_distances(near=True) of a scene without a pair list: the broad phase's candidates at q (ascending)
  // with their distances, coal's query on Python's objects (data.Data.distance); every other pair is +inf. NaN where
  // coal's query failed (a distance neither below C_.distance_failed in size nor +inf)
  std::vector<std::pair<int, double>> near_distances(const VectorXd &q) {
    place_geometries(q);
    std::vector<int> cand;
    candidates(cand);
    for (int k : cand) table_guess(k);
    std::vector<std::pair<int, double>> out;
    out.reserve(cand.size());
    for (int k : cand) {
      const double x = table_distance(k);
      out.push_back({k, (std::abs(x) < C_.distance_failed || x == INFINITY) ? x : std::numeric_limits<double>::quiet_NaN()});
    }
    return out;
  }
  // contacts.geometry_gaps (a model of more than model.GAP_PAIRS pairs: the records' gaps, one per geometry) into
  // out: each geometry's least distance to the geometries it pairs with where it is at most gap_reach_ [m], else +inf;
  // NaN where coal's query of a pair failed (np.minimum's: a NaN stays). coal's query on the candidates at
  // gap_margin_: pinocchio's computeDistance on the GeometryData (a pair list), or on Python's objects
  // (data.Data.distance_query, table mode), their guesses journaled (journal_distance)
  void geometry_gaps(const VectorXd &q, double *out) {
    place_geometries(q);
    std::vector<int> &cand = gap_cand_;
    candidates(cand, gap_margin_);
    const size_t G = gm_.geometryObjects.size();
    std::fill(out, out + G, INFINITY);
    for (int k : cand) {
      if (table_)
        table_guess(k);
      else
        fresh_guess(gd_.distanceRequests[(size_t)k].cached_gjk_guess);
    }
    const double nan = std::numeric_limits<double>::quiet_NaN();
    for (int k : cand) {
      const pairs::Row r = pair(k);
      double x = table_ ? table_distance(k) : pinocchio::computeDistance(gm_, gd_, (pinocchio::PairIndex)k).min_distance;
      if (!(std::abs(x) < C_.distance_failed)) x = nan;
      if (x > gap_reach_) x = INFINITY;  // a candidate beyond the reach: as the others
      for (const int g : {r.first, r.second}) out[g] = (std::isnan(out[g]) || std::isnan(x)) ? nan : std::min(out[g], x);
    }
  }
  // a table pair's distance query (Python's coal objects, data.Data.distance_query) before its first use at a new
  // configuration: its guesses journaled (journal_distance), then made fresh as contacts.fresh_guesses makes them
  void table_guess(int k) {
    journal_distance(k);
    fresh_guess(distance_of(k).req->cached_gjk_guess);
  }
  // coal's distance of table pair k at the placed geometries (min_distance as coal returns it)
  double table_distance(int k) {
    const DistanceQuery d = distance_of(k);
    const pairs::Row r = table_->row(k);
    d.res->clear();
    (*d.f)(placement(r.first), placement(r.second), *d.req, *d.res);
    return d.res->min_distance;
  }
  // the distance queries' guesses a step and its sample move in table mode (Python's objects, not the GeometryData's:
  // the run loop's Undo restores them, src/run.cpp): journal_begin() before the step, each query's guesses saved at
  // its first use after it, journal_restore() puts them back
  void journal_begin() { journal_on_ = true, journal_.clear(); }
  void journal_end() { journal_on_ = false, journal_.clear(); }
  void journal_distance(int k) {
    if (!journal_on_ || journal_.count(k)) return;
    const DistanceQuery d = distance_of(k);
    journal_[k] = SavedDistance{d.req->cached_gjk_guess, d.req->cached_support_func_guess, d.res->cached_gjk_guess,
                                d.res->cached_support_func_guess};
  }
  void journal_restore() {
    for (const auto &[k, saved] : journal_) {
      const DistanceQuery d = distance_of(k);
      d.req->cached_gjk_guess = saved.req, d.req->cached_support_func_guess = saved.req_hint;
      d.res->cached_gjk_guess = saved.res, d.res->cached_support_func_guess = saved.res_hint;
    }
    journal_.clear();
  }
  // the correction's guard above (stepper.correct_positions) in table mode, with contacts.pair_distances(near=True):
  // no pair deeper at q_c than its floor min(distance at q_next, 0) (+ half the depth a paid lift lifts, scaled) less
  // tol; a pair not among the candidates at q_next has distance +inf (floor 0), not among those at q_c: +inf
  bool near_distances_hold(const VectorXd &q_next, const VectorXd &q_c, const std::vector<Found> &con,
                           const VectorXd &g_next, bool scaled) {
    const auto before = near_distances(q_next), after = near_distances(q_c);
    std::unordered_map<int, double> lifted;  // np.minimum.at(lifted, pair, g_next) from 0, the pairs it touches
    if (scaled)
      for (size_t i = 0; i < con.size(); ++i) {
        const Eigen::Index p = con[i].pair;
        if (p < 0 || p >= npairs()) continue;
        const auto it = lifted.find((int)p);
        const double l = it == lifted.end() ? 0.0 : it->second, gi = g_next[(Eigen::Index)i];
        lifted[(int)p] = nan_min(l, gi);
      }
    for (const auto &[k, a] : after) {
      const auto it = std::lower_bound(before.begin(), before.end(), std::pair<int, double>(k, -INFINITY));
      const double b = (it != before.end() && it->first == k) ? it->second : INFINITY;
      double floor = std::isnan(b) ? b : std::min(b, 0.0);
      if (scaled) {
        const auto l = lifted.find(k);
        floor = floor + 0.5 * (l == lifted.end() ? 0.0 : l->second);
      }
      if (a < floor - tol_) return false;
    }
    return true;
  }
  coal::Transform3s placement(int g) const {
    const auto &o = gd_.oMg[(size_t)g];
    return coal::Transform3s(o.rotation(), o.translation());
  }

  // the pairs: as many as the list's rows or the table's; pair k's geometries and joints; two polytopes
  Eigen::Index npairs() const { return table_ ? (Eigen::Index)table_->size() : pairs_.rows(); }
  pairs::Row pair(Eigen::Index k) const {
    if (table_) return table_->row(k);
    return {(int)pairs_(k, 0), (int)pairs_(k, 1), (int)pairs_(k, 2), (int)pairs_(k, 3), pairs_(k, 4) != 0};
  }
  bool polytope(Eigen::Index k) const {
    if (table_) return table_->polytope(table_->row(k));
    return k < (Eigen::Index)polytope_.size() && polytope_[(size_t)k];
  }
  // pair k's coal collision objects: the GeometryData's, or (table mode) Python's, made by it at first use
  CollisionQuery collision_of(int k) {
    if (!table_)
      return {&gd_.collisionRequests[(size_t)k], &gd_.collisionResults[(size_t)k], &gd_.collision_functors[(size_t)k]};
    return made<coal::CollisionRequest, coal::CollisionResult, coal::ComputeCollision>(cq_, collide_query_, k,
                                                                                       "Collision");
  }
  DistanceQuery distance_of(int k) {
    return made<coal::DistanceRequest, coal::DistanceResult, coal::ComputeDistance>(dq_, distance_query_, k,
                                                                                    "Distance");
  }
  // pair k's (request, result, functor) as make(k), Python's Data, makes them at first use: cached, the objects kept
  template <class Req, class Res, class F, class Q>
  Q made(std::unordered_map<int, Q> &cache, const nb::object &make, int k, const std::string &kind) {
    const auto it = cache.find(k);
    if (it != cache.end()) return it->second;
    const nb::tuple t = nb::cast<nb::tuple>(make(k));
    if (t.size() != 3) throw nb::value_error((kind + " query: (request, result, functor) expected").c_str());
    query_keep_.push_back(t);
    const Q q{&extract_ref<Req>(t[0], ("coal." + kind + "Request").c_str()),
              &extract_ref<Res>(t[1], ("coal." + kind + "Result").c_str()),
              &extract_ref<F>(t[2], ("coal.Compute" + kind).c_str())};
    return cache[k] = q;
  }
  // coal's collision query of pair k: pinocchio's computeCollision, or (table mode) the same query on Python's objects
  // as data.Data.collide makes it (pinocchio's distance_upper_bound, a cleared result, the pair's functor)
  bool collide(int k) {
    if (!table_) return pinocchio::computeCollision(gm_, gd_, (pinocchio::PairIndex)k);
    const CollisionQuery c = collision_of(k);
    const pairs::Row r = table_->row(k);
    c.req->distance_upper_bound = c.req->security_margin + 1e-6;
    c.res->clear();
    (*c.f)(placement(r.first), placement(r.second), *c.req, *c.res);
    return c.res->isCollision();
  }

  // contacts.fresh_guesses, operation by operation: a cached GJK guess shorter than C_.guess_min (or
  // non-finite) is rescaled to unit length, (1, 0, 0) if it has no direction (coal 3.0.3 fails from a
  // guess of ~1e-12 m: a deep overlap reported as no collision, a distance of -DBL_MAX)
  template <typename Requests>
  void fresh_guesses(Requests &requests) const {
    for (auto &req : requests) fresh_guess(req.cached_gjk_guess);
  }

  // contacts.fresh_guesses on one request's guess
  void fresh_guess(coal::Vec3s &g) const {
    const double x = g[0], y = g[1], z = g[2];
    if (std::max(std::max(std::abs(x), std::abs(y)), std::abs(z)) >= C_.guess_min && std::isfinite(x + y + z)) return;
    const double n = std::sqrt(x * x + y * y + z * z);
    if (0.0 < n && n < std::numeric_limits<double>::infinity())
      g = coal::Vec3s(x / n, y / n, z / n);
    else
      g = coal::Vec3s(1.0, 0.0, 0.0);
  }

  // coal's GJK warm start of a collision query: its functor's solver, its request's and its result's cached guesses
  // (what Python's detection, rerun after a fallback, starts from)
  struct Guesses {
    coal::Vec3s solver, request, result;
    coal::support_func_guess_t solver_hint, request_hint, result_hint;
  };
  std::vector<Guesses> saved_;
  std::vector<int> saved_pairs_;  // the pairs saved_ holds (saved_all_: every pair, in order)
  bool saved_all_ = true;
  void save_one(Guesses &s, size_t k) {
    const CollisionQuery c = collision_of((int)k);
    const coal::GJKSolver &sv = (*c.f).*SolverOf::member();
    const auto &rq = *c.req;
    const auto &rs = *c.res;
    s = {sv.cached_guess, rq.cached_gjk_guess, rs.cached_gjk_guess, sv.support_func_cached_guess,
         rq.cached_support_func_guess, rs.cached_support_func_guess};
  }
  void restore_one(const Guesses &s, size_t k) {
    const CollisionQuery c = collision_of((int)k);
    coal::GJKSolver &sv = (*c.f).*SolverOf::member();
    auto &rq = *c.req;
    auto &rs = *c.res;
    sv.cached_guess = s.solver, sv.support_func_cached_guess = s.solver_hint;
    rq.cached_gjk_guess = s.request, rq.cached_support_func_guess = s.request_hint;
    rs.cached_gjk_guess = s.result, rs.cached_support_func_guess = s.result_hint;
  }
  // before a detection of every pair
  void save_guesses() {
    const size_t n = gd_.collision_functors.size();
    saved_all_ = true, saved_.resize(n);
    for (size_t k = 0; k < n; ++k) save_one(saved_[k], k);
    if (dres_) saved_dres_ = *dres_;
  }
  // before a detection of these pairs (the broad phase's candidates): the others keep theirs
  void save_guesses(const std::vector<int> &pairs) {
    saved_all_ = false, saved_pairs_ = pairs, saved_.resize(pairs.size());
    for (size_t s = 0; s < pairs.size(); ++s) save_one(saved_[s], (size_t)pairs[s]);
    if (dres_) saved_dres_ = *dres_;
  }
  void restore_guesses() {
    if (saved_all_)
      for (size_t k = 0; k < saved_.size() && k < gd_.collision_functors.size(); ++k) restore_one(saved_[k], k);
    else
      for (size_t s = 0; s < saved_.size(); ++s) restore_one(saved_[s], (size_t)saved_pairs_[s]);
    if (dres_) *dres_ = saved_dres_;
  }

  // stepper.free_velocity (tau_: the step's joint torques, or zero)
  VectorXd free_velocity(const VectorXd &q_m, const VectorXd &u, double h) {
    const VectorXd zero = tau_.size() ? tau_ : VectorXd::Zero(model_.nv);
    VectorXd a = aba(q_m, u, zero);
    VectorXd u_free = u + h * a;
    if (!bias_midpoint_ || !velocity_bias_) return u_free;
    const double scale = C_.midpoint_tolerance * (1.0 + u.cwiseAbs().maxCoeff());
    for (int it = 0; it < C_.midpoint_iterations; ++it) {
      VectorXd ubar = 0.5 * (u + u_free);
      a = aba(q_m, ubar, zero);
      VectorXd nxt = u + h * a;
      bool done = (nxt - u_free).cwiseAbs().maxCoeff() <= scale;
      u_free = nxt;
      if (done) break;
    }
    return u_free;
  }

  // box_box.depth_floor of two boxes at their placements oMg (contacts._boxes)
  double box_floor(int first, int second) const {
    const auto &o1 = gd_.oMg[first], &o2 = gd_.oMg[second];
    return boxbox::depth_floor(o1.rotation(), o1.translation(), half_[first], o2.rotation(), o2.translation(),
                               half_[second], C_.parallel, C_.depth_ratio, tol_);
  }

  // contacts._vertex_contacts for one geometry's vertices against another
  void vertex_contacts(int g_vert, int joint_v, int g_other, int joint_other, std::vector<Found> &out, int pair,
                       int offset, bool v_is_a, double margin) {
    const MatrixXd &V = vertices_[g_vert];
    if (V.rows() == 0) return;
    const auto &oMi = forest_.oMi((size_t)joint_v), &oMo = forest_.oMi((size_t)joint_other);
    const Eigen::Matrix3d &R = oMi.rotation();
    const Vec3 &t = oMi.translation();
    MatrixXd Vw(V.rows(), 3);  // ordered(V, R.T) + t
    for (Eigen::Index i = 0; i < V.rows(); ++i)
      for (int j = 0; j < 3; ++j) Vw(i, j) = odot(&V(i, 0), R.data() + j, 3, V.rows(), 3) + t[j];
    const Vec3 &a = bound_a_[g_other];
    const double b = bound_b_[g_other];
    const Eigen::Matrix3d &Ro = oMo.rotation();
    const Vec3 &to = oMo.translation();
    if (bound_kind_[g_other] == 0) {  // a half-space: exact signed distances
      Vec3 n;  // ordered(Ro, a)
      for (int j = 0; j < 3; ++j) n[j] = odot(Ro.data() + j, a.data(), 3, 3, 1);
      const double c = b + odot(n.data(), to.data(), 3);
      for (Eigen::Index i = 0; i < V.rows(); ++i) {
        const double d = odot(&Vw(i, 0), n.data(), 3, V.rows(), 1) - c;  // ordered(Vw, n) - c
        if (!(d <= tol_)) continue;
        Vec3 p = Vw.row(i).transpose();
        Vec3 dn = d * n;
        if (v_is_a)
          out.push_back({d, p, p - dn, n, pair, C_.vertex, offset + (int)i});
        else
          out.push_back({d, p - dn, p, -n, pair, C_.vertex, offset + (int)i});
      }
      return;
    }
    // a bounding sphere: the vertices within tol of it get coal's point query (the functor Python calls,
    // data.point_query); a vertex at two or more of a box's faces (a corner, _corner_normals) goes to Python
    Vec3 ctr;
    for (int j = 0; j < 3; ++j) ctr[j] = odot(Ro.data() + j, a.data(), 3, 3, 1) + to[j];
    coal::ComputeDistance *query = shapes_ ? query_[g_other] : nullptr;
    for (Eigen::Index i = 0; i < V.rows(); ++i) {
      const Vec3 dv = Vw.row(i).transpose() - ctr;
      const double est = std::sqrt((dv[0] * dv[0] + dv[1] * dv[1]) + dv[2] * dv[2]) - b;
      if (!query) {
        if (est <= tol_ + 1e-9 * (1.0 + std::abs(b))) throw Fallback{"vertex near a shape that is no half-space"};
        continue;
      }
      if (!(est <= tol_)) continue;
      coal::Transform3s tf;  // data.point_tf: identity rotation, the vertex's translation
      tf.setTranslation(Vw.row(i).transpose());
      const auto &oMg = gd_.oMg[g_other];
      const coal::Transform3s tf_other(oMg.rotation(), oMg.translation());
      double d = (*query)(tf, tf_other, *dreq_, *dres_);
      if (!(d <= tol_)) continue;
      const Vec3 nrm_coal = dres_->normal;  // from the vertex towards the other shape
      Vec3 p_other = dres_->nearest_points[1];
      const boxbox::RowsX3 &Pn = plane_n_[g_other];
      const VectorXd &Pd = plane_d_[g_other];
      if (!(nrm_coal.allFinite() && std::abs(d) < 1e100)) {
        if (Pn.rows() == 0 || std::abs(d) >= 1e100) continue;  // no face to take the normal of: coal's pair contact
        throw Fallback{"a vertex on a box's surface (no coal normal)"};
      }
      Vec3 nrm = nrm_coal;
      const int k_cone = cone_[g_vert];
      if (Pn.rows() && k_cone >= 0) {
        // contacts._corner_normals: the faces within margin of the largest signed distance; of those, the faces whose
        // planes leave the vertex's own cone (its edges, vedges_) outside: two or more make a corner (Python's
        // set-valued law); one gives the contact its face normal; none, coal's normal. A face whose plane the edges cross
        // (by more than 1e-9) still separates when the vertex's body lies outside it to tol_ (§6.2, 1c: a tilted cube's
        // vertex at the other's top corner). A vertex outside the box within
        // margin of one face plane only is over that face (the others' planes are behind it): the face's normal, the
        // exact one, not coal's (at a gap of 1e-17 m coal's pointed 0.45 rad off: issue 23)
        const Vec3 pl = boxbox::rt_times(Ro, Vw.row(i).transpose() - to);  // sums.dots(R.T, x)'s sums
        VectorXd sd(Pn.rows());
        for (Eigen::Index f = 0; f < Pn.rows(); ++f) sd[f] = ((Pn(f, 0) * pl[0] + Pn(f, 1) * pl[1]) + Pn(f, 2) * pl[2]) - Pd[f];
        std::vector<Eigen::Index> on;
        for (Eigen::Index f = 0; f < sd.size(); ++f)
          if (sd[f] >= sd.maxCoeff() - margin) on.push_back(f);
        if (on.size() >= 2) {
          const Eigen::Matrix3d &Rv = oMi.rotation();
          const boxbox::RowsX3 &VE = vedges_[g_vert];  // vertex i's edges in rows k_cone i .. k_cone i + k_cone - 1
          int ok = 0;
          Vec3 first;
          Eigen::Index f_first = -1;
          for (Eigen::Index f : on) {
            const Vec3 nw = boxbox::row_rt(Pn, f, Ro);
            double lo = INFINITY;
            for (int k = 0; k < k_cone; ++k) lo = std::min(lo, boxbox::dot3(nw, boxbox::row_rt(VE, k_cone * i + k, Rv)));
            bool sep = lo >= -1e-9;  // contacts._corner_normals' literal
            if (!sep) {  // the vertex's body outside face f's plane to tol_: it separates (docs/theory.md §6.2, 1c)
              double lo_body = INFINITY;
              for (Eigen::Index j = 0; j < V.rows(); ++j) {
                const Vec3 pj = boxbox::rt_times(Ro, Vw.row(j).transpose() - to);
                lo_body = std::min(lo_body, ((Pn(f, 0) * pj[0] + Pn(f, 1) * pj[1]) + Pn(f, 2) * pj[2]) - Pd[f]);
              }
              sep = lo_body >= -tol_;
            }
            if (sep) {
              if (!ok) first = nw, f_first = f;
              ++ok;
            }
          }
          if (ok >= 2) throw Fallback{"a vertex at a box's edge or corner"};
          if (ok == 1) {
            nrm = -first;
            if (sd[f_first] < sd.maxCoeff() - tol_) {  // beyond tol of the nearest face's: its plane's gap (§6.2, 1d)
              d = sd[f_first];
              p_other = Vw.row(i).transpose() + d * nrm;
            }
          }
        } else if (sd.maxCoeff() > 0.0) {  // outside, over one face only (its projection inside it): that face's normal
          nrm = -boxbox::row_rt(Pn, on[0], Ro);
        }
      }
      const Vec3 p = Vw.row(i).transpose();
      if (v_is_a)
        out.push_back({d, p, p_other, -nrm, pair, C_.vertex, offset + (int)i});
      else
        out.push_back({d, p_other, p, nrm, pair, C_.vertex, offset + (int)i});
    }
  }

  // contacts._snap: the face normal of A or B (outward, oriented B -> A; face_n_ in the joint frames) nearest to coal's
  // normal n, if its cosine exceeds C_.snap (the first largest of each shape's, A's then B's), else n; the products are
  // sums.ordered's (ordered3), as Python's
  Vec3 snap(int first, int jf, int second, int js, const Vec3 &n) const {
    Vec3 best = n;
    double cos_best = C_.snap;
    const int g_of[2] = {first, second}, j_of[2] = {jf, js};
    const double sign_of[2] = {-1.0, 1.0};
    for (int s = 0; s < 2; ++s) {
      const boxbox::RowsX3 &F = face_n_[g_of[s]];
      if (!F.rows()) continue;
      const Eigen::Matrix3d &R = rot(j_of[s]);
      Vec3 w_best;
      double c_max = 0.0;
      for (Eigen::Index f = 0; f < F.rows(); ++f) {
        const Vec3 w = sign_of[s] * boxbox::row_rt_ordered(F, f, R);
        const double c = boxbox::ordered3(w.data(), n.data(), 1, 1);
        if (f == 0 || c > c_max) c_max = c, w_best = w;  // np.argmax: the first largest
      }
      if (c_max > cos_best) best = w_best, cos_best = c_max;
    }
    return best;
  }

  // contacts._twin: row r (a vertex of B on A's face) is one of found[start, mid) (A's vertices on B's face, the same
  // pair) at the same touching point: its point on A within C_.same_point and its normal within contacts.TWIN_NORMAL
  // (box_box.CONE, C_.cone) in every component (max-norms; docs/theory.md §6.2, 1b)
  bool twin(const std::vector<Found> &found, size_t start, size_t mid, const Found &r) const {
    for (size_t j = start; j < mid; ++j)
      if ((found[j].pa - r.pa).cwiseAbs().maxCoeff() <= C_.same_point &&
          (found[j].n - r.n).cwiseAbs().maxCoeff() <= C_.cone)
        return true;
    return false;
  }
  // whether point p (on A) is farther than C_.same_point (max-norm) from every point on A of found[start:]
  bool new_point(const std::vector<Found> &found, size_t start, const Vec3 &p) const {
    for (size_t j = start; j < found.size(); ++j)
      if ((found[j].pa - p).cwiseAbs().maxCoeff() <= C_.same_point) return false;
    return true;
  }
  // contacts._add_new: the edge crossings and face corners whose point on A is no contact of found[start:] yet (a
  // patch corner of two yawed faces is also the crossing of their edges), and of the face corners those that are
  // no such crossing either, appended in their order
  void add_new(std::vector<Found> &found, size_t start, std::vector<Found> &edges) const {
    if (edges.empty()) return;
    std::vector<Found> fresh;
    for (const Found &r : edges)
      if (new_point(found, start, r.pa)) fresh.push_back(r);
    for (const Found &r : fresh) {
      bool keep = r.kind == C_.edge;
      if (!keep) {
        keep = true;
        for (const Found &x : fresh)
          if (x.kind == C_.edge && !((x.pa - r.pa).cwiseAbs().maxCoeff() > C_.same_point)) keep = false;
      }
      if (keep) found.push_back(r);
    }
  }
  const Eigen::Matrix3d &rot(int joint) const { return forest_.oMi((size_t)joint).rotation(); }
  const Vec3 &trans(int joint) const { return forest_.oMi((size_t)joint).translation(); }

  // broad_phase.BroadPhase.candidates_at (the sums of sums.dots, in its order) at the forest's placements oMi: into
  // out, the sorted pairs whose inflated boxes overlap, with a half-space within the margin, or always examined
  void candidates(std::vector<int> &out) { candidates(out, bp_->margin); }
  // the same at another margin [m] (broad_phase.within's BroadPhase(model, m).margin: m + SLACK): the records' gaps
  void candidates(std::vector<int> &out, double margin) {
    const BroadPhase &B = *bp_;
    const Eigen::Index G = (Eigen::Index)B.joint.size();
    bp_c_.resize(G, 3), bp_h_.resize(G, 3);
    for (Eigen::Index g = 0; g < G; ++g) {
      const Eigen::Matrix3d &R = rot(B.joint[g]);
      const Vec3 &t = trans(B.joint[g]);
      for (int i = 0; i < 3; ++i) {
        bp_c_(g, i) = (((R(i, 0) * B.centre(g, 0) + R(i, 1) * B.centre(g, 1)) + R(i, 2) * B.centre(g, 2)) + 0.0) + t[i];
        bp_h_(g, i) = ((std::abs(R(i, 0)) * B.half(g, 0) + std::abs(R(i, 1)) * B.half(g, 1)) +
                       std::abs(R(i, 2)) * B.half(g, 2)) + 0.0;
      }
    }
    out.assign(B.always.begin(), B.always.end());
    // _sweep: every two bounded geometries whose boxes, inflated by the margin, overlap (the same set whichever the
    // axis of the sweep: the one where the boxes spread most)
    const size_t nb = B.bounded.size();
    if (nb >= 2 && (table_ || !B.index.empty())) {
      std::vector<Eigen::Index> b(B.bounded.begin(), B.bounded.end());
      Eigen::Matrix<double, Eigen::Dynamic, 3> lo(nb, 3), hi(nb, 3);
      for (size_t a = 0; a < nb; ++a)
        for (int i = 0; i < 3; ++i) {
          lo(a, i) = (bp_c_(b[a], i) - bp_h_(b[a], i)) - margin;
          hi(a, i) = (bp_c_(b[a], i) + bp_h_(b[a], i)) + margin;
        }
      int axis = 0;
      double spread = -1.0;
      for (int i = 0; i < 3; ++i) {
        const double s = lo.col(i).maxCoeff() - lo.col(i).minCoeff();
        if (s > spread) spread = s, axis = i;
      }
      std::vector<size_t> order(nb);
      for (size_t a = 0; a < nb; ++a) order[a] = a;
      std::stable_sort(order.begin(), order.end(), [&](size_t x, size_t y) { return lo(x, axis) < lo(y, axis); });
      const int64_t nG = G;
      for (size_t a = 0; a < nb; ++a) {
        const size_t i = order[a];
        for (size_t k = a + 1; k < nb && lo(order[k], axis) <= hi(i, axis); ++k) {
          const size_t j = order[k];
          if (!(lo(i, 0) <= hi(j, 0) && lo(j, 0) <= hi(i, 0) && lo(i, 1) <= hi(j, 1) && lo(j, 1) <= hi(i, 1) &&
                lo(i, 2) <= hi(j, 2) && lo(j, 2) <= hi(i, 2)))
            continue;
          const int64_t lo = std::min(b[i], b[j]), hi = std::max(b[i], b[j]);
          if (table_) {
            if (table_->chosen(lo, hi)) out.push_back((int)table_->index(lo, hi));
            continue;
          }
          const auto it = B.index.find(lo * nG + hi);
          if (it != B.index.end()) out.push_back(it->second);
        }
      }
    }
    for (size_t k = 0; k < B.half_pair.size(); ++k) {  // a half-space's pairs: the other's box within the margin
      const int hg = B.half_geom[k], o = B.half_other[k];
      const Eigen::Matrix3d &R = rot(B.joint[hg]);
      const Vec3 &t = trans(B.joint[hg]);
      Vec3 n;
      for (int i = 0; i < 3; ++i)
        n[i] = ((R(i, 0) * B.half_n(k, 0) + R(i, 1) * B.half_n(k, 1)) + R(i, 2) * B.half_n(k, 2)) + 0.0;
      const double d = B.half_d[k] + (((n[0] * t[0] + n[1] * t[1]) + n[2] * t[2]) + 0.0);
      const double nc = ((n[0] * bp_c_(o, 0) + n[1] * bp_c_(o, 1)) + n[2] * bp_c_(o, 2)) + 0.0;
      const double nh = ((std::abs(n[0]) * bp_h_(o, 0) + std::abs(n[1]) * bp_h_(o, 1)) + std::abs(n[2]) * bp_h_(o, 2)) + 0.0;
      if ((nc - nh) - d <= margin) out.push_back(B.half_pair[k]);
    }
    std::sort(out.begin(), out.end());
    out.erase(std::unique(out.begin(), out.end()), out.end());
  }

  // contacts.detect: coal's narrow phase on every pair (a model of more than broad_phase.MIN_PAIRS pairs: on the broad
  // phase's candidates, in pair order), and (box models) the box pairs with contacts at the last detection still
  // within tol (_near_polytopes, warm_); a pair's corner margin: max(tol, the sum of its joints' joint_travel), or tol
  // without it (contacts.detect's corner_margin)
  std::vector<Found> detect(const VectorXd &q_m, const std::vector<double> *joint_travel) {
    std::vector<Found> found;
    place_geometries(q_m);
    next_warm_ = warm_;
    const Eigen::Index np = npairs();
    if (np == 0) return found;
    std::vector<int> hits;  // the pairs coal's narrow phase finds colliding, ascending
    if (bp_) {
      candidates(cand_);
      save_guesses(cand_);
      for (int k : cand_) fresh_guess(collision_of(k).req->cached_gjk_guess);
      for (int k : cand_)
        if (collide(k)) hits.push_back(k);
    } else {
      if (table_) throw Fallback{"a scene without a pair list and no broad phase"};
      save_guesses();
      fresh_guesses(gd_.collisionRequests);
      pinocchio::computeCollisions(gm_, gd_, false);
      for (Eigen::Index k = 0; k < np; ++k)
        if (gd_.collisionResults[(size_t)k].isCollision()) hits.push_back((int)k);
    }
    std::vector<int> near;  // ascending, as warm_
    for (int k : warm_) {  // _near_polytopes: model.polytope_pair_ids, two geometries with vertices and bounding spheres
      if (k >= np || !shapes_) continue;
      const pairs::Row p = pair(k);
      const int g1 = p.first, g2 = p.second, j1 = p.joint_first, j2 = p.joint_second;
      if (bound_kind_[g1] != 1 || bound_kind_[g2] != 1 || !vertices_[g1].rows() || !vertices_[g2].rows()) continue;
      const Vec3 d = (rot(j1) * bound_a_[g1] + trans(j1)) - (rot(j2) * bound_a_[g2] + trans(j2));
      if (std::sqrt(d.dot(d)) - bound_b_[g1] - bound_b_[g2] <= tol_) near.push_back(k);
    }
    std::vector<int> todo;  // sorted(hits | near)
    std::set_union(hits.begin(), hits.end(), near.begin(), near.end(), std::back_inserter(todo));
    for (const int k : todo) {
      const bool hit = std::binary_search(hits.begin(), hits.end(), k);
      const pairs::Row p = pair(k);
      const int first = p.first, second = p.second, jf = p.joint_first, js = p.joint_second;
      const double margin =
          joint_travel ? std::max(tol_, (*joint_travel)[(size_t)jf] + (*joint_travel)[(size_t)js]) : tol_;
      const bool patch = p.patch;
      const size_t start = found.size();
      const int na = (int)vertices_[first].rows(), nb_ = (int)vertices_[second].rows();
      if (na) vertex_contacts(first, jf, second, js, found, (int)k, 0, true, margin);
      const size_t mid = found.size();
      if (nb_) vertex_contacts(second, js, first, jf, found, (int)k, na, false, margin);
      if (start < mid && mid < found.size())  // a vertex of B at a vertex of A on the same face: A's row (contacts._twin)
        found.erase(std::remove_if(found.begin() + (std::ptrdiff_t)mid, found.end(),
                                   [&](const Found &r) { return twin(found, start, mid, r); }),
                    found.end());
      // contacts._edge_contacts: the edge crossings (EDGE, 12 k + l), then the corners of nearly parallel faces (FACE)
      // of two boxes; a corner of this pair has handed the step back already (vertex_contacts), so contacts.detect's
      // filter of crossings at a corner has nothing to filter here
      std::vector<Found> edges;
      if (shapes_ && is_box_[first] && is_box_[second]) {
        const auto cands = boxbox::edge_candidates(edges_[first], rot(jf), trans(jf), edges_[second], rot(js),
                                                   trans(js), tol_, C_.cone, C_.edge_end, C_.parallel);
        double floor = -INFINITY;  // crossed far deeper than the boxes' penetration depth: no contact
        bool crossed = false;
        for (const auto &x : cands) crossed = crossed || x.g < 0.0;
        if (crossed) floor = box_floor(first, second);
        for (const auto &x : cands)
          if (x.g >= floor) edges.push_back({x.g, x.pa, x.pb, x.n, (int)k, x.face ? C_.face : C_.edge, x.feature});
      }
      if (hit) {
        const auto &c = collision_of(k).res->getContact(0);
        const Vec3 n = -c.normal;
        const double depth = c.penetration_depth;
        if (!(std::abs(depth) < 1e100 && std::isfinite(n.dot(n)))) throw Fallback{"coal's contact needs the EPA fallback"};
        // contacts._too_deep: two boxes' contact deeper than box_box.depth_floor is coal's EPA failing
        if (depth < -tol_ && shapes_ && is_box_[first] && is_box_[second] && depth < box_floor(first, second))
          throw Fallback{"coal's contact needs the EPA fallback"};
        size_t k_patch = 0;
        if (patch && depth <= tol_) {
          if (!shapes_) throw Fallback{"contact patch"};
          // the patch about the face normal nearest to coal's: two polytopes' face axis, else the face normal within
          // contacts._SNAP of coal's normal (contacts._snap)
          const Vec3 n_face = polytope(k) ? boxbox::face_axis(vertices_[first], rot(jf), trans(jf), face_n_[first],
                                                               vertices_[second], rot(js), trans(js), face_n_[second])
                                           : snap(first, jf, second, js, n);
          // with vertex contacts, the patch must lie in their plane (contacts.detect's literal 1 - 1e-9)
          if (found.size() == start || n_face.dot(found[start].n) >= 1.0 - 1e-9) {
            coal::CollisionResult cres;
            const coal::CollisionGeometry *g1 = gm_.geometryObjects[first].geometry.get();
            const coal::CollisionGeometry *g2 = gm_.geometryObjects[second].geometry.get();
            cres.addContact(coal::Contact(g1, g2, -1, -1, c.pos, -n_face, depth));
            coal::ContactPatchResult pres(*preq_);
            const auto &o1 = gd_.oMg[first], &o2 = gd_.oMg[second];
            coal::computeContactPatch(g1, coal::Transform3s(o1.rotation(), o1.translation()), g2,
                                      coal::Transform3s(o2.rotation(), o2.translation()), cres, *preq_, pres);
            const coal::ContactPatch &pt = pres.getContactPatch(0);
            k_patch = pt.size();
            if (k_patch > 1) {
              // coal's polygon: the face corners are its corners (docs/theory.md §6.2)
              edges.erase(std::remove_if(edges.begin(), edges.end(), [&](const Found &r) { return r.kind == C_.face; }),
                          edges.end());
              std::vector<Vec3> P1(k_patch);
              std::vector<char> fresh(k_patch);
              for (size_t i = 0; i < k_patch; ++i) P1[i] = pt.getPointShape1(i), fresh[i] = new_point(found, start, P1[i]);
              for (size_t i = 0; i < k_patch; ++i)
                if (fresh[i]) found.push_back({depth, P1[i], pt.getPointShape2(i), n_face, (int)k, C_.patch, (int)i});
            }
          }
        }
        if (k_patch <= 1 && found.size() == start && edges.empty() && depth <= tol_)  // no vertex: smooth shapes
          found.push_back({depth, c.nearest_points[0], c.nearest_points[1], n, (int)k, C_.witness, 0});
      }
      add_new(found, start, edges);
    }
    next_warm_.clear();
    for (const Found &f : found)
      if (next_warm_.empty() || next_warm_.back() != f.pair) next_warm_.push_back(f.pair);
    std::sort(next_warm_.begin(), next_warm_.end());
    next_warm_.erase(std::unique(next_warm_.begin(), next_warm_.end()), next_warm_.end());
    return found;
  }

  // constraints.closed_limits: the joint limits with g = sign (q_i - bound) <= tol, appended (pair, kind, feature:
  // the limit's pair index, JOINT_LIMIT, its joint; no points, zero normals)
  // limits.JointLimit.gap: limit k's g(q) = sign (q_i - bound) [rad or m]
  double limit_gap(const VectorXd &q, Eigen::Index k) const {
    return limits_(k, 4) * (q[(Eigen::Index)limits_(k, 2)] - limits_(k, 5));
  }
  void closed_limits(const VectorXd &q_m, std::vector<Found> &found) const {
    for (Eigen::Index k = 0; k < limits_.rows(); ++k) {
      const double g = limit_gap(q_m, k);
      if (g <= tol_)
        found.push_back({g, Vec3::Zero(), Vec3::Zero(), Vec3::Zero(), (int)limits_(k, 0), C_.joint_limit,
                         (int)limits_(k, 1)});
    }
  }
  // the correction's guard on the joint limits (stepper._guarded: their gaps after the pairs' distances, at their pair
  // indices): no limit's gap at q_c below its floor min(gap at q_next, 0) (+ half the least g_next of its rows where
  // a paid lift lifts them, scaled) less tol
  bool limits_hold(const VectorXd &q_next, const VectorXd &q_c, const std::vector<Found> &con, const VectorXd &g_next,
                   bool scaled) const {
    const Eigen::Index nl = limits_.rows();
    if (!nl) return true;
    VectorXd lifted = VectorXd::Zero(nl);  // np.minimum.at(lifted, pair, g_next) from 0 (the limits' entries)
    if (scaled)
      for (size_t i = 0; i < con.size(); ++i) {
        const Eigen::Index k = (Eigen::Index)con[i].pair - (Eigen::Index)limits_(0, 0);
        if (k < 0 || k >= nl) continue;
        lifted[k] = nan_min(lifted[k], g_next[(Eigen::Index)i]);
      }
    for (Eigen::Index k = 0; k < nl; ++k) {
      double floor = std::min(limit_gap(q_next, k), 0.0);
      if (scaled) floor = floor + 0.5 * lifted[k];
      if (limit_gap(q_c, k) < floor - tol_) return false;
    }
    return true;
  }
  // a contact's joints (A, B): its pair's, or a joint limit's (its joint, the world)
  std::pair<int, int> joints_of(const Found &f) const {
    if (f.kind == C_.joint_limit) return {f.feature, 0};
    const pairs::Row p = pair(f.pair);
    return {p.joint_first, p.joint_second};
  }

  // constraints.contact_rows: w = mask_a (n'J_lin + (p_a x n)'J_ang) - mask_b (same at p_b), summed as sums.ordered,
  // on the velocities that move body a or b (support_); +0.0 on the others. wi (if given): W's nonzeros, as
  // WInfo::set finds them (no second pass over W)
  // written (if given): the rows written in each column (ptr, rows; the others +0.0)
  MatrixXd contact_rows(const std::vector<Found> &f, WInfo *wi = nullptr,
                        std::pair<std::vector<Eigen::Index>, std::vector<Eigen::Index>> *written = nullptr) {
    const Eigen::Index nv = model_.nv, m = (Eigen::Index)f.size();
    const auto &J = J_;  // (6, nv) WORLD (crba_world)
    MatrixXd W = Spare::take(spare_->mu, spare_->W, nv, m, true);  // +0.0 but where written below
    bool finite = true;
    if (wi) wi->wptr.assign((size_t)m + 1, 0), wi->widx.clear();
    if (written) written->first.assign(1, 0), written->second.clear();
    for (Eigen::Index i = 0; i < m; ++i) {
      if (f[i].kind == C_.joint_limit) {  // the constant row sign e_{idx_v}
        const Eigen::Index k = f[i].pair - npairs();
        const Eigen::Index v = (Eigen::Index)limits_(k, 3);
        W(v, i) = limits_(k, 4);
        finite = finite && std::isfinite(W(v, i));
        if (wi && W(v, i) != 0.0) wi->widx.push_back(v);
        if (wi) wi->wptr[(size_t)i + 1] = (Eigen::Index)wi->widx.size();
        if (written) written->second.push_back(v), written->first.push_back((Eigen::Index)written->second.size());
        continue;
      }
      const pairs::Row p = pair(f[i].pair);
      const std::vector<Eigen::Index> &sa = support_[(size_t)p.joint_first], &sb = support_[(size_t)p.joint_second];
      const Vec3 &n = f[i].n;
      Vec3 c[2];
      for (int s = 0; s < 2; ++s) {
        const Vec3 &p = s == 0 ? f[i].pa : f[i].pb;
        c[s] = Vec3(p[1] * n[2] - p[2] * n[1], p[2] * n[0] - p[0] * n[2], p[0] * n[1] - p[1] * n[0]);
      }
      size_t a = 0, b = 0;  // the two supports merged, ascending
      while (a < sa.size() || b < sb.size()) {
        Eigen::Index v;
        double ma = 0.0, mb = 0.0;  // mask_a, mask_b at v
        if (b == sb.size() || (a < sa.size() && sa[a] < sb[b]))
          v = sa[a++], ma = 1.0;
        else if (a == sa.size() || sb[b] < sa[a])
          v = sb[b++], mb = 1.0;
        else
          v = sa[a++], ++b, ma = mb = 1.0;
        const double lin = ((n[0] * J(0, v) + n[1] * J(1, v)) + n[2] * J(2, v)) + 0.0;
        double side[2];
        for (int s = 0; s < 2; ++s)
          side[s] = lin + (((c[s][0] * J(3, v) + c[s][1] * J(4, v)) + c[s][2] * J(5, v)) + 0.0);
        const double w = side[0] * ma - side[1] * mb;
        W(v, i) = w;
        finite = finite && std::isfinite(w);
        if (wi && w != 0.0) wi->widx.push_back(v);
        if (written) written->second.push_back(v);
      }
      if (wi) wi->wptr[(size_t)i + 1] = (Eigen::Index)wi->widx.size();
      if (written) written->first.push_back((Eigen::Index)written->second.size());
    }
    if (wi) {
      wi->finite = finite;
      if (!finite) wi->wptr.assign((size_t)m + 1, 0), wi->widx.clear();  // WInfo::set's lists of a W not finite
    }
    return W;
  }

  // constraints.distinct: drop a contact whose row repeats an earlier one (to C_.distinct relative)
  std::vector<int> distinct(const MatrixXd &W, const WInfo *wi = nullptr) const { return distinct_rows(W, C_.distinct, wi); }

  Solved project(const MatrixXd &W, const VectorXd &v0, const VectorXd &b, const MatrixXd &Minv) {
    return ::project(C_, W, v0, b, Minv);
  }

  // ---- the driven joints' step (moreau_sim/drive_step.py, docs/theory.md §2.13), operation by operation
  static VectorXd take(const VectorXd &x, const std::vector<Eigen::Index> &i) {
    VectorXd y((Eigen::Index)i.size());
    for (size_t k = 0; k < i.size(); ++k) y[(Eigen::Index)k] = x[i[k]];
    return y;
  }
  static MatrixXd take(const MatrixXd &A, const std::vector<Eigen::Index> &i, const std::vector<Eigen::Index> &j) {
    MatrixXd B((Eigen::Index)i.size(), (Eigen::Index)j.size());
    for (size_t a = 0; a < i.size(); ++a)
      for (size_t c = 0; c < j.size(); ++c) B((Eigen::Index)a, (Eigen::Index)c) = A(i[a], j[c]);
    return B;
  }
  static std::vector<Eigen::Index> all(Eigen::Index n) {
    std::vector<Eigen::Index> i((size_t)n);
    for (Eigen::Index k = 0; k < n; ++k) i[(size_t)k] = k;
    return i;
  }
  // drive_step._inverse: A^-1 column by column (lu_solve of the unit vectors)
  static MatrixXd inverse(const MatrixXd &A) {
    const Eigen::Index n = A.rows();
    MatrixXd X(n, n);
    VectorXd x;
    for (Eigen::Index j = 0; j < n; ++j) {
      if (!lu_solve(A, VectorXd::Unit(n, j), x)) throw Fallback{"a driven step's mass matrix is singular"};
      X.col(j) = x;
    }
    return X;
  }
  // drive_step.DriveStep
  struct DriveStep {
    VectorXd xdot, u_f, u_c, ubar;  // xdot(t_{k+1}), the unconstrained free velocity, the driven one, (u_d^k + xdot)/2
    MatrixXd Md;  // M's driven rows
    double work_free = 0.0;
    // DriveStep.work: ubar_d' [M (u_next - u_f)]_d
    double work(const VectorXd &u_next) const {
      const VectorXd y = otimes(Md, VectorXd(u_next - u_f));
      return odot(ubar.data(), y.data(), ubar.size());
    }
  };
  // drive_step.start: the driven free velocity u_c (u_free: the unconstrained one, the midpoint's last on return)
  DriveStep drive_start(const MatrixXd &M, const VectorXd &q_m, const VectorXd &u, VectorXd &u_free, double t_m,
                        double h) {
    const auto &r = rh_.r, &d = rh_.d;
    if (r.empty()) throw Fallback{"every joint driven"};
    DriveStep ds;
    rh_.drive_velocity(t_m + 0.5 * h, ds.xdot);
    const MatrixXd Mrr = take(M, r, r), Mrd = take(M, r, d);
    // u_f,r + M_rr^-1 M_rd (u_f,d - xdot)
    auto free_rows = [&](const VectorXd &uf) {
      const VectorXd y = take(uf, d) - ds.xdot;
      VectorXd s;
      if (!lu_solve(Mrr, otimes(Mrd, y), s)) throw Fallback{"a driven step's mass matrix is singular"};
      return VectorXd(take(uf, r) + s);
    };
    ds.u_c = u_free;
    for (size_t j = 0; j < d.size(); ++j) ds.u_c[d[j]] = ds.xdot[(Eigen::Index)j];
    VectorXd ur = free_rows(u_free);
    for (size_t j = 0; j < r.size(); ++j) ds.u_c[r[j]] = ur[(Eigen::Index)j];
    if (velocity_bias_ && bias_midpoint_) {  // b at the driven step's own mean (§2.4)
      const VectorXd zero = tau_.size() ? tau_ : VectorXd::Zero(model_.nv);
      const double scale = C_.midpoint_tolerance * (1.0 + u.cwiseAbs().maxCoeff());
      for (int it = 0; it < C_.midpoint_iterations; ++it) {
        const VectorXd ubar = 0.5 * (u + ds.u_c);
        u_free = u + h * aba(q_m, ubar, zero);
        const VectorXd nxt = free_rows(u_free);
        double dmax = 0.0;  // np.abs(nxt - u_c[r]).max(initial=0.0), NaN kept
        for (size_t j = 0; j < r.size(); ++j) {
          const double a = std::abs(nxt[(Eigen::Index)j] - ds.u_c[r[j]]);
          if (!(a <= dmax)) dmax = a;
        }
        const bool done = dmax <= scale;
        for (size_t j = 0; j < r.size(); ++j) ds.u_c[r[j]] = nxt[(Eigen::Index)j];
        if (done) break;
      }
    }
    ds.u_f = u_free;
    ds.ubar = 0.5 * (take(u, d) + ds.xdot);
    ds.Md = take(M, d, all(model_.nv));
    ds.work_free = ds.work(ds.u_c);
    return ds;
  }

  void step_(const VectorXd &q, const VectorXd &u, double h, double e, double t, StepOut &out) {
    const Eigen::Index nv = model_.nv;
    if (q.size() != model_.nq || u.size() != nv) throw nb::value_error("q, u: sizes nq, nv expected");
    VectorXd q_m = pinocchio::integrate(model_, q, (0.5 * h) * u);
    const double t_m = t + 0.5 * h;  // the force evaluation: obstacles and drives at t_m (§2.1, §2.9)
    if (!rh_.moving.empty()) rh_.place(const_cast<pinocchio::GeometryModel &>(gm_), t_m);  // Prescribed.place
    const bool driven = rh_.driven();
    const double travel = h * (nv ? u.cwiseAbs().maxCoeff() : 0.0) * reach_;
    // trees.Forest.joint_travel: each joint's tree's h |u_tree|_inf reach, the world's 0 (the corner margins)
    thread_local std::vector<double> tree_travel, joint_travel;
    const auto &trees = forest_.trees();
    tree_travel.assign(trees.size(), 0.0);
    for (size_t k = 0; k < trees.size(); ++k)
      if (trees[k].nv) tree_travel[k] = h * u.segment(trees[k].v0, trees[k].nv).cwiseAbs().maxCoeff() * reach_;
    const auto &tree_of = forest_.tree_of_joint();
    joint_travel.resize(tree_of.size());
    for (size_t j = 0; j < tree_of.size(); ++j) joint_travel[j] = tree_of[j] < 0 ? 0.0 : tree_travel[(size_t)tree_of[j]];
    std::vector<Found> found = detect(q_m, &joint_travel);
    if (tunnelling_ == 2 || (tunnelling_ == 0 && travel > thinnest_)) throw Fallback{"swept detection"};
    closed_limits(q_m, found);
    if (found.empty()) {
      VectorXd u_free = free_velocity(q_m, u, h);
      if (driven) {  // u_{k+1} = u_c; the drive's work in the step booked (§5.5)
        const DriveStep ds = drive_start(crba_world(q_m), q_m, u, u_free, t_m, h);
        u_free = ds.u_c;
        out.obstacle_work = ds.work_free;
      }
      out.q_next = pinocchio::integrate(model_, q_m, (0.5 * h) * u_free);
      out.u_next = u_free;
      out.u_free = std::move(u_free);
      out.outcome = Outcome::FLIGHT;
      return;
    }
    // constraints.assemble_constraints: M by CRBA (fills the WORLD Jacobians), rows, distinct rows
    const MatrixXd &M = crba_world(q_m);  // M_ itself (no copy): nothing below makes M again
    thread_local WInfo wi0, wli;  // W0's nonzeros (contact_rows); Wl's: its products W'x over them (otimes_t_nz)
    std::pair<std::vector<Eigen::Index>, std::vector<Eigen::Index>> wr0, wr;  // the rows written (contact_rows)
    MatrixXd W0 = contact_rows(found, &wi0, &wr0);
    std::vector<int> keep = distinct(W0, &wi0);
    const Eigen::Index m = (Eigen::Index)keep.size();
    MatrixXd W;
    std::vector<Found> con;
    if (m == W0.cols()) {  // every row distinct: W is W0 (no copy)
      W = std::move(W0), con = std::move(found);
      std::swap(wli, wi0), std::swap(wr, wr0);
    } else {  // the kept columns' written entries (the others +0.0 in both)
      W = Spare::take(spare_->mu, spare_->W, nv, m, true);
      wli.finite = wi0.finite, wli.wptr.assign(1, 0), wli.widx.clear();
      wr.first.assign(1, 0), wr.second.clear();
      for (Eigen::Index j = 0; j < m; ++j) {
        con.push_back(found[keep[j]]);
        const size_t c = (size_t)keep[j];
        for (Eigen::Index t = wr0.first[c]; t < wr0.first[c + 1]; ++t) {
          const Eigen::Index v = wr0.second[(size_t)t];
          W(v, j) = W0(v, keep[j]), wr.second.push_back(v);
        }
        wr.first.push_back((Eigen::Index)wr.second.size());
        wli.widx.insert(wli.widx.end(), wi0.widx.begin() + wi0.wptr[c], wi0.widx.begin() + wi0.wptr[c + 1]);
        wli.wptr.push_back((Eigen::Index)wli.widx.size());
      }
      Spare::clear(W0, wr0.first, wr0.second);
      Spare::give(spare_->mu, spare_->W, W0);
    }
    // Prescribed.rates: dg_i/dt = -n_i.V(t_m) of the contacts against a moving static (§2.9); none: no rate
    VectorXd rate;
    bool has_rate = false;
    if (!rh_.moving.empty()) {
      Vec3 V;
      for (Eigen::Index i = 0; i < m; ++i) {
        if (con[i].kind == C_.joint_limit) continue;
        const pairs::Row p = pair(con[i].pair);
        for (int s = 0; s < 2; ++s) {  // the normal points from second to first
          if (!rh_.velocity((size_t)(s == 0 ? p.second : p.first), t_m, V)) continue;
          if (!has_rate) rate = VectorXd::Zero(m), has_rate = true;
          const Vec3 &n = con[i].n;
          rate[i] = rate[i] + (s == 0 ? -1.0 : 1.0) * (((n[0] * V[0] + n[1] * V[1]) + n[2] * V[2]) + 0.0);
        }
      }
    }
    // the problem the law is solved in (stepper.assemble): every velocity row, or a driven step's free rows
    // (DriveStep.reduced: W_r, M_rr, the rate W_d' (xdot + e u_d^k)/(1 + e) added)
    MatrixXd Minv_d, Wk;  // Minv_d: the driven step's M_rr^-1
    const MatrixXd *Minvp = &Minv_d;  // M^-1: Minv_ itself (no copy), or Minv_d
    VectorXd u_free, v_free, uk, ufk, vfk;
    DriveStep ds;
    MatrixXd Mrr;
    if (!driven) {
      Minvp = &minverse(q_m);
      u_free = free_velocity(q_m, u, h);
      v_free = (u_free + e * u) / (1.0 + e);
    } else {
      u_free = free_velocity(q_m, u, h);
      ds = drive_start(M, q_m, u, u_free, t_m, h);
      u_free = ds.u_c;
      v_free = (u_free + e * u) / (1.0 + e);
      const VectorXd y = (ds.xdot + e * take(u, rh_.d)) / (1.0 + e);
      const VectorXd rd = otimes_t(take(W, rh_.d, all(m)), y);
      rate = has_rate ? VectorXd(rate + rd) : rd;
      has_rate = true;
      Wk = take(W, rh_.r, all(m));
      for (Eigen::Index i = 0; i < m; ++i)
        if (!(Wk.col(i).array() != 0.0).any()) throw Fallback{"a contact only driven joints move"};
      Mrr = take(M, rh_.r, rh_.r);
      Minv_d = inverse(Mrr);
      uk = take(u, rh_.r), ufk = take(u_free, rh_.r), vfk = take(v_free, rh_.r);
    }
    const MatrixXd &Minv = *Minvp;
    const MatrixXd &Wl = driven ? Wk : W;
    const VectorXd &ul = driven ? uk : u, &ufl = driven ? ufk : u_free, &vfl = driven ? vfk : v_free;
    // solve_impact
    if (driven) wli.set(Wl);  // Wl = W_r; else W, whose lists contact_rows made (shared with project)
    VectorXd gamma_minus;
    otimes_t_nz(Wl, wli, ul, gamma_minus);
    if (has_rate) gamma_minus = gamma_minus + rate;  // gamma = W'u + dg/dt (§2.9)
    VectorXd b = VectorXd::Zero(m);  // law.restitution_bounds (None -> b = 0 in qp.solve)
    bool any = false;
    {
      VectorXd e_i = VectorXd::Constant(m, e);
      if (sep_elastic_ && e < 1.0 && std::max(0.0, gamma_minus.maxCoeff()) > 0.0) {
        any = true;
        for (Eigen::Index i = 0; i < m; ++i) e_i[i] = gamma_minus[i] > 0.0 ? 1.0 : e;
      }
      if (slow_plastic_ && e > 0.0 && std::min(0.0, gamma_minus.minCoeff()) < 0.0) {
        VectorXd du = ufl - ul;
        VectorXd wdu;
        otimes_t_nz(Wl, wli, du, wdu);
        bool slow_any = false;
        for (Eigen::Index i = 0; i < m; ++i) {
          if (gamma_minus[i] < 0.0 && gamma_minus[i] >= wdu[i]) slow_any = true, e_i[i] = 0.0;
        }
        any = any || slow_any;
      }
      if (any)
        for (Eigen::Index i = 0; i < m; ++i) b[i] = ((e - e_i[i]) * gamma_minus[i]) / (1.0 + e);
    }
    if (has_rate) b = any ? VectorXd(b - rate) : VectorXd(-rate);
    // stepper.warm_start: above C_.sparse_rows rows the rows whose (pair, kind, feature) pushed at the last step
    std::vector<char> start;
    const bool warm = m > C_.sparse_rows;
    if (warm && !active_.empty()) {
      start.assign((size_t)m, 0);
      for (Eigen::Index i = 0; i < m; ++i)
        start[(size_t)i] = std::binary_search(active_.begin(), active_.end(),
                                              std::array<int64_t, 3>{con[i].pair, con[i].kind, con[i].feature});
    }
    Solved res = ::project(C_, Wl, vfl, b, Minv, start.empty() ? nullptr : &start, &wli, driven ? nullptr : &blocks_);
    if (warm && (Eigen::Index)res.act.size() == m) {  // stepper.keep_active: the first pass's final set
      for (Eigen::Index i = 0; i < m; ++i)
        if (res.act[(size_t)i]) next_active_.push_back({con[i].pair, con[i].kind, con[i].feature});
      std::sort(next_active_.begin(), next_active_.end());
    }
    VectorXd u_next = res.v - e * (ul - res.v);
    VectorXd P = (1.0 + e) * res.lam;
    VectorXd gamma_plus;
    otimes_t_nz(Wl, wli, u_next, gamma_plus);
    double ow = 0.0;  // the obstacle work -P.dg/dt (§5.5)
    if (has_rate) {
      gamma_plus = gamma_plus + rate;
      ow = -odot(P.data(), rate.data(), m);
    }
    VectorXd gsum = gamma_plus + gamma_minus;
    const double work = odot(P.data(), gsum.data(), m) * 0.5;
    VectorXd v = std::move(res.v), v0 = v_free;
    MatrixXd Mout, Minv_c;  // the driven step's embedded M_rr (the StepOut's M; else M itself, copied in at the end)
    if (driven) {  // DriveStep.expanded: u_{k+1} = (u_r, xdot), W's driven rows zero, the QP's problem embedded
      VectorXd U(nv), ve(nv), v0e(nv);
      MatrixXd We = MatrixXd::Zero(nv, m);
      Mout.setZero(nv, nv);
      for (size_t j = 0; j < rh_.r.size(); ++j) {
        const Eigen::Index rj = rh_.r[j], jj = (Eigen::Index)j;
        U[rj] = u_next[jj], ve[rj] = v[jj], v0e[rj] = vfk[jj];
        We.row(rj) = Wk.row(jj);
        for (size_t k = 0; k < rh_.r.size(); ++k) Mout(rj, rh_.r[k]) = Mrr(jj, (Eigen::Index)k);
      }
      for (size_t j = 0; j < rh_.d.size(); ++j) {
        const Eigen::Index dj = rh_.d[j];
        U[dj] = ve[dj] = v0e[dj] = ds.xdot[(Eigen::Index)j];
      }
      u_next = std::move(U), v = std::move(ve), v0 = std::move(v0e), W = std::move(We);
      ow = ow + ds.work(u_next);
      if (projection_) {  // DriveStep.for_correction: M block-diagonal (M_rr, M_dd)
        MatrixXd Mc = MatrixXd::Zero(nv, nv);
        for (const auto *rows : {&rh_.r, &rh_.d})
          for (Eigen::Index i : *rows)
            for (Eigen::Index k : *rows) Mc(i, k) = M(i, k);
        Minv_c = inverse(Mc);
      }
    }
    VectorXd q_next = pinocchio::integrate(model_, q_m, (0.5 * h) * u_next);
    double corr = 0.0;
    VectorXd g(m);
    for (Eigen::Index i = 0; i < m; ++i) g[i] = con[i].g;
    if (projection_)  // a paid lift (§2.5): u_next, gamma_plus those of the lift, out.u_law the law's u_{k+1}
      out.paid = correct_positions(q, u, u_free, h, g, gamma_plus, u_next, M, W, driven ? Minv_c : Minv, q_next,
                                   corr, gamma_minus, con, ow, out.u_law, res.act, driven ? nullptr : &wli);
    if (!driven)  // §2.10 (a driven joint: §2.13), with the torques' and the moving statics' work
      cap_energy(q, u, q_m, u_free, h, e, P, work, corr, W, q_next, u_next, gamma_plus, ow,
                 has_rate ? &rate : nullptr, &wli);
    out.outcome = Outcome::CONTACT;
    out.q_next = std::move(q_next), out.u_next = std::move(u_next), out.u_free = std::move(u_free);
    out.g = std::move(g);
    out.point_a.resize(m, 3), out.point_b.resize(m, 3), out.normal.resize(m, 3);
    out.pair.resize(m), out.kind.resize(m), out.feature.resize(m), out.joint_a.resize(m), out.joint_b.resize(m);
    for (Eigen::Index i = 0; i < m; ++i) {
      out.point_a.row(i) = con[i].pa.transpose(), out.point_b.row(i) = con[i].pb.transpose();
      out.normal.row(i) = con[i].n.transpose();
      out.pair[i] = con[i].pair, out.kind[i] = con[i].kind, out.feature[i] = con[i].feature;
      const auto jab = joints_of(con[i]);
      out.joint_a[i] = jab.first, out.joint_b[i] = jab.second;
    }
    out.P = std::move(P), out.gamma_minus = std::move(gamma_minus), out.gamma_plus = std::move(gamma_plus);
    out.v_free = std::move(v0), out.b = std::move(b), out.v = std::move(v), out.lam = std::move(res.lam);
    out.set_M(driven ? Mout : M, blocks_);  // the trees' blocks (the driven step's M_rr embedded: zero off them too)
    out.W = std::move(W), out.projection = res.status;
    if (!driven) out.wptr = std::move(wr.first), out.wrow = std::move(wr.second);  // driven: W embedded (unknown)
    out.contact_work = work, out.correction_energy = corr, out.m = m;
    out.obstacle_work = ow, out.drive_work_free = driven ? ds.work_free : 0.0;
  }

  // stepper._roundoff
  double roundoff(double T0, double V0, double T1, double V1) const {
    return C_.energy_roundoff * (((T0 + std::abs(V0)) + T1) + std::abs(V1));
  }
  // stepper._trees: the velocity indices of every kinematic tree (the joints below one child of the universe)
  // that W's rows involve
  // (wi: W's nonzeros where known; cols: the columns of W read, all where null)
  std::vector<bool> trees(const MatrixXd &W, const WInfo *wi = nullptr,
                          const std::vector<Eigen::Index> *cols = nullptr) const {
    std::vector<int> tree(model_.nv, 0);
    for (int j = 1; j < model_.njoints; ++j) {
      int root = j;
      while (model_.parents[root] != 0) root = (int)model_.parents[root];
      const int iv = model_.joints[j].idx_v(), nvj = model_.joints[j].nv();
      for (int k = iv; k < iv + nvj; ++k) tree[k] = root;
    }
    std::vector<bool> hit(model_.njoints, false), involved(model_.nv, false);
    auto column = [&](Eigen::Index i) { nonzero_rows(W, wi, i, [&](Eigen::Index j) { hit[tree[j]] = true; }); };
    if (cols)
      for (Eigen::Index i : *cols) column(i);
    else
      for (Eigen::Index i = 0; i < W.cols(); ++i) column(i);
    for (int k = 0; k < model_.nv; ++k) involved[k] = hit[tree[k]];
    return involved;
  }
  // f(j) for each j with W(j, i) != 0.0 (NaN included), ascending: by wi's lists where W is finite, else every entry
  template <class F> static void nonzero_rows(const MatrixXd &W, const WInfo *wi, Eigen::Index i, F &&f) {
    if (wi && wi->finite) {
      for (Eigen::Index t = wi->wptr[(size_t)i]; t < wi->wptr[(size_t)i + 1]; ++t) f(wi->widx[(size_t)t]);
      return;
    }
    for (Eigen::Index j = 0; j < W.rows(); ++j)
      if (W(j, i) != 0.0) f(j);
  }
  // stepper._split: u = u_S + u_R, u_S the velocities of the trees W's rows involve; a = T(q, u_S), T_R = T(q, u_R)
  // [J], the terms of T(q, u_R + alpha u_S) = a alpha^2 + b alpha + T_R (docs/theory.md §2.10); T_R only where a > 0
  struct Split {
    VectorXd u_S, u_R;
    double a, T_R;
  };
  Split split(const MatrixXd &W, const VectorXd &q, const VectorXd &u, const WInfo *wi) {
    const std::vector<bool> involved = trees(W, wi);
    Split s{VectorXd::Zero(u.size()), VectorXd(), 0.0, std::numeric_limits<double>::quiet_NaN()};
    for (Eigen::Index j = 0; j < u.size(); ++j)
      if (involved[j]) s.u_S[j] = u[j];
    s.u_R = u - s.u_S;
    s.a = kinetic(q, s.u_S);
    if (s.a > 0.0) s.T_R = kinetic(q, s.u_R);
    return s;
  }
  // stepper._alpha: the largest root of a alpha^2 + b alpha + c in [floor, 1], else the alpha of least value
  static double alpha_of(double a, double b, double c, double floor) {
    const double disc = b * b - (4.0 * a) * c;
    const double alpha = disc >= 0.0 ? (std::sqrt(disc) - b) / (2.0 * a) : -b / (2.0 * a);  // else: the least value
    return std::min(1.0, std::max(floor, alpha));
  }

  // stepper.cap_energy (docs/theory.md §2.10): T + V <= E* + W_a (tau_: the torques' work h tau.(u_k + u_{k+1})/2,
  // linear in alpha), + max(S_k, 0) in a step that bounces under torques, + W_o (ow: a moving static's work, P fixed);
  // the trees in contact scaled by alpha where the step ends above, no lower than a moving static's rate keeps
  // gamma's sign (rate: its dg/dt, nullptr: none)
  void cap_energy(const VectorXd &q, const VectorXd &u, const VectorXd &q_m, const VectorXd &u_free, double h,
                  double e, const VectorXd &P, double work, double corr, const MatrixXd &W, const VectorXd &q_next,
                  VectorXd &u_next, VectorXd &gamma_plus, double ow, const VectorXd *rate, const WInfo *wi) {
    const double T0 = kinetic(q, u);
    const double V0 = potential(q);
    const double T1 = kinetic(q_next, u_next);
    const double V1 = potential(q_next);
    double target = (((T0 + V0) + std::min(work, 0.0)) + corr) + ow;  // W_o: P fixed, no alpha
    const bool driven = tau_.size() != 0;
    // stepper.bounces_under_torques: a driven step whose contacts bounce (e > 0) may keep the smooth step's gain
    if (driven && e > 0.0 && (P.array() > 0.0).any())
      target = target + std::max(smooth_error(q_m, u, u_free, h, T0 + V0), 0.0);
    VectorXd f;
    double wa = 0.0;
    if (driven) {
      f = (0.5 * h) * tau_;
      const VectorXd s = u + u_next;
      wa = odot(f.data(), s.data(), model_.nv);
    }
    if (T1 + V1 <= (target + wa) + roundoff(T0, V0, T1, V1)) return;
    const Split sp = split(W, q_next, u_next, wi);
    if (!(sp.a > 0.0)) return;
    const VectorXd &u_S = sp.u_S, &u_R = sp.u_R;
    const double a = sp.a, T_R = sp.T_R;
    double b = (T1 - a) - T_R;
    double c = T_R - (target - V1);
    if (driven) {  // the torques' work f.(u_k + u_R) + alpha f.u_S
      const VectorXd s = u + u_R;
      b = b - odot(f.data(), u_S.data(), model_.nv);
      c = c - odot(f.data(), s.data(), model_.nv);
    }
    double floor = 0.0;
    if (rate) {  // a moving static: gamma = alpha W'u_S + dg/dt keeps its sign
      const VectorXd wu = otimes_t(W, u_S);
      for (Eigen::Index i = 0; i < wu.size(); ++i)
        if ((*rate)[i] < 0.0 && gamma_plus[i] >= 0.0 && wu[i] > 0.0) {
          const double f = -(*rate)[i] / wu[i];
          if (f > floor) floor = f;
        }
    }
    const double alpha = alpha_of(a, b, c, std::min(floor, 1.0));
    u_next = u_R + alpha * u_S;
    gamma_plus = otimes_t(W, u_next);
    if (rate) gamma_plus = gamma_plus + *rate;
  }

  // stepper.smooth_error (docs/theory.md §5.3, §5.5): T + V at (q_m (+) h/2 u_free, u_free) less E = T_k + V_k and
  // the torques' work h tau.(u_k + u_free)/2
  double smooth_error(const VectorXd &q_m, const VectorXd &u, const VectorXd &u_free, double h, double E) {
    const VectorXd q_free = pinocchio::integrate(model_, q_m, (0.5 * h) * u_free);
    double S = energy(q_free, u_free) - E;
    if (tau_.size() != 0) {
      const VectorXd f = (0.5 * h) * tau_;
      const VectorXd s = u + u_free;
      S = S - odot(f.data(), s.data(), model_.nv);
    }
    return S;
  }

  // stepper.correct_positions, and stepper.step's use of a lift paid with the velocities (§2.5): true where it paid
  // one (u_next, gamma_plus then those of the lift's u_{k+1}, ordered(W', u_c); u_law the law's u_{k+1} before it)
  bool correct_positions(const VectorXd &q, const VectorXd &u, const VectorXd &u_free, double h, const VectorXd &g,
                         VectorXd &gamma_plus, VectorXd &u_next, const MatrixXd &M, const MatrixXd &W,
                         const MatrixXd &Minv, VectorXd &q_next, double &corr, const VectorXd &gamma_minus,
                         const std::vector<Found> &con, double ow, VectorXd &u_law, const std::vector<char> &law_act,
                         const WInfo *wi) {  // wi: W's nonzeros where the law's lists are W's (not driven)
    (void)M;
    const Eigen::Index m = g.size();
    VectorXd g_next = g + (0.5 * h) * gamma_plus;
    if (m == 0 || g_next.minCoeff() >= -tol_) return false;
    const double T0 = kinetic(q, u);
    const double V0 = potential(q);
    const double E0 = T0 + V0;
    const double E1 = energy(q_next, u_next);
    double budget = E0 - E1 + ow;  // what the step dissipated beyond the work done on it (§5.5)
    if (tau_.size()) {  // what the step dissipated beyond the torques' work h tau.(u + u_next)/2 (theory §5.5)
      const VectorXd s = u + u_next;
      budget += 0.5 * h * odot(tau_.data(), s.data(), model_.nv);
    }
    // stepper._resting: the bodies of every penetrating contact end the step at rest
    // (|u_next_j| <= resting max|u_free - u| wherever a penetrating row has w_ij != 0)
    bool resting = true;
    double dmax = 0.0;
    for (Eigen::Index j = 0; j < u.size(); ++j) dmax = std::max(dmax, std::abs(u_free[j] - u[j]));
    const double eps = C_.resting * dmax;
    std::vector<char> involved(W.rows(), 0);
    for (Eigen::Index i = 0; i < m; ++i)  // (W column-major: each penetrating row's column in memory order)
      if (g_next[i] < -tol_) nonzero_rows(W, wi, i, [&](Eigen::Index j) { involved[j] = 1; });
    for (Eigen::Index j = 0; j < W.rows() && resting; ++j)
      if (involved[j]) resting = std::abs(u_next[j]) <= eps;
    Solved res;
    bool solved = false;
    if (!resting) {
      // stepper._normal_rest: every closed contact of those bodies (a row with w_ij != 0 at an involved j) has
      // |gamma^k| <= eps and |gamma^{k+1}| <= eps, and their trees' kinetic energy does not change: lifted in full,
      // each of those contacts kept within hold tolerances (theory §2.5)
      std::vector<Eigen::Index> rows;
      bool still = true;
      for (Eigen::Index i = 0; i < m && still; ++i) {
        bool row = false;
        nonzero_rows(W, wi, i, [&](Eigen::Index j) { row = row || involved[j]; });
        if (!row) continue;
        rows.push_back(i);
        still = std::abs(gamma_minus[i]) <= eps && std::abs(gamma_plus[i]) <= eps;
      }
      if (still) {  // and the kinetic energy of their trees changes by at most resting T(q_k, u_free - u_k)
        std::vector<Eigen::Index> pen;
        for (Eigen::Index i = 0; i < m; ++i)
          if (g_next[i] < -tol_) pen.push_back(i);
        const std::vector<bool> S = trees(W, wi, &pen);  // the trees of the penetrating rows
        VectorXd u1 = VectorXd::Zero(u.size()), u0 = VectorXd::Zero(u.size()), du = VectorXd::Zero(u.size());
        for (Eigen::Index j = 0; j < u.size(); ++j)
          if (S[j]) u1[j] = u_next[j], u0[j] = u[j], du[j] = u_free[j] - u[j];
        const double dT = kinetic(q_next, u1) -
                          kinetic(q, u0);
        still = std::abs(dT) <= C_.resting * kinetic(q, du);
      }
      if (still) {
        const Eigen::Index k = (Eigen::Index)rows.size();
        MatrixXd Wn(W.rows(), m + k);
        VectorXd bn(m + k);
        Wn.leftCols(m) = W;
        bn.head(m) = -g_next;
        for (Eigen::Index c = 0; c < k; ++c) {
          const Eigen::Index i = rows[c];
          Wn.col(m + c) = -W.col(i);
          bn[m + c] = g_next[i] - std::max(g_next[i], C_.hold * tol_);
        }
        res = project(Wn, VectorXd::Zero(model_.nv), bn, Minv);  // Fallback where its active set does not settle
        solved = resting = true;
      }
    }
    // stepper.correct_positions' paid lift: a persistent penetration between flat faces (deeper than h |gamma_minus|
    // + tol; stepper._flat: two polytopes, or a polytope's vertex on a half-space) in a passive step is lifted in
    // full, paid with the velocities, also in a step that gained (below)
    bool deep = false, persistent = tau_.size() == 0 && rh_.moving.empty() && !rh_.driven();
    for (Eigen::Index i = 0; i < m && persistent; ++i)
      if (g_next[i] < -(h * std::abs(gamma_minus[i]) + tol_)) {
        deep = true;
        const int p = con[i].pair;
        persistent = con[i].kind != C_.joint_limit &&
                     (polytope(p) || (con[i].kind == C_.vertex && p < npairs() &&
                                      (bound_kind_[pair(p).first] == 0 || bound_kind_[pair(p).second] == 0)));
      }
    persistent = persistent && deep;
    if (budget <= 0.0 && !resting && !persistent) return false;
    if (!solved)  // above C_.sparse_rows rows warm-started from the law's final set (stepper.correct_positions, §2.5)
      res = ::project(C_, W, VectorXd::Zero(model_.nv), -g_next, Minv,
                      (Eigen::Index)law_act.size() == m ? &law_act : nullptr, wi,
                      rh_.driven() ? nullptr : &blocks_);  // a driven step's Minv: DriveStep.for_correction's
    VectorXd q_c = pinocchio::integrate(model_, q_next, res.v);
    const double T_c = kinetic(q_c, u_next);
    const double V_c = potential(q_c);
    double dE = T_c + V_c - E1;
    VectorXd u_c;  // the paid lift's u_{k+1} (stepper._scaled), where `scaled`; else u_next itself
    bool scaled = false;
    if (dE > budget && !resting) {
      bool paid = false;
      if (persistent) {  // the full lift, paid in full with the kinetic energy of the bodies in contact: T + V ends
        // where the law's step ended, E_1 (§2.5). stepper._scaled(q_c, u_next, the rows' trees, E_1 - V_c, T_c):
        // u_R + alpha u_S (stepper._split, _alpha with floor 0), u_next itself where T(q_c, u_S) is not positive
        const Split sp = split(W, q_c, u_next, wi);
        if (sp.a > 0.0) {
          u_c = sp.u_R + alpha_of(sp.a, (T_c - sp.a) - sp.T_R, sp.T_R - (E1 - V_c), 0.0) * sp.u_S;
          scaled = true;
        }
        dE = (kinetic(q_c, scaled ? u_c : u_next) + V_c) - E1;
        paid = dE <= roundoff(T0, V0, T_c, V_c);
      }
      if (!paid && budget <= 0.0) return false;  // a step that gained: nothing to spend
      if (!paid) {  // (alpha from the dE of the scaled velocities where a lift was tried: as stepper.py has it)
        scaled = false;
        double alpha = budget / dE;  // E is ~linear in dq here
        q_c = pinocchio::integrate(model_, q_next, alpha * res.v);
        dE = energy(q_c, u_next) - E1;
        if (dE > budget + roundoff(T0, V0, T_c, V_c)) {  // concave along dq: shortened by the relative excess twice
          alpha *= (budget / dE) * (budget / dE);
          q_c = pinocchio::integrate(model_, q_next, alpha * res.v);
          dE = energy(q_c, u_next) - E1;
        }
        if (dE > budget) return false;
      }
    }
    if (table_) {
      if (!near_distances_hold(q_next, q_c, con, g_next, scaled)) return false;
    } else {
    const VectorXd before = pair_distances(q_next), after = pair_distances(q_c);
    VectorXd floor = before.cwiseMin(0.0);  // np.minimum(before, 0.0): NaN kept
    for (Eigen::Index k = 0; k < floor.size(); ++k)
      if (std::isnan(before[k])) floor[k] = before[k];
    if (scaled) {  // a paid lift: a pair it lifts may go deeper at a feature that was not closed, by at most half the
      // depth it lifts (§2.5): floor + 0.5 lifted, lifted the least g_next of the pair's contacts (np.minimum.at from 0)
      VectorXd lifted = VectorXd::Zero(floor.size());
      for (Eigen::Index i = 0; i < m; ++i) {
        const Eigen::Index p = con[i].pair;
        if (p < 0 || p >= floor.size()) continue;  // own = pair < len(floor)
        const double l = lifted[p], gi = g_next[i];
        lifted[p] = nan_min(l, gi);
      }
      floor = floor + 0.5 * lifted;
    }
    for (Eigen::Index k = 0; k < before.size(); ++k)
      if (after[k] < floor[k] - tol_) return false;
    }
    if (!limits_hold(q_next, q_c, con, g_next, scaled)) return false;
    q_next = q_c;
    corr = dE;
    if (!scaled) return false;
    u_law = std::move(u_next);  // stepper.step: u_law = imp.u_next; u_{k+1} = u_c, gamma_plus = ordered(W', u_c)
    u_next = std::move(u_c);
    gamma_plus = otimes_t(W, u_next);
    return true;
  }
};

#include "owned.hpp"  // results as NumPy arrays over their own storage (the adaptive integrator's calls)
#include "run.cpp"  // the run loop over a Stepper (moreau_sim/compiled_run.py)
#include "events.hpp"  // the adaptive integrator's extrapolated step (moreau_sim/compiled_events.py)
#include "adaptive.hpp"  // the adaptive integrator's samples on its dense output (moreau_sim/compiled_events.py)
#include "impact.hpp"  // the impact at a located event (moreau_sim/compiled_events.py)
#include "locate.hpp"  // the adaptive integrator's event location in free flight (moreau_sim/compiled_events.py)
#include "phase.hpp"  // the adaptive integrator's step in free flight in one call (moreau_sim/compiled_events.py)

NB_MODULE(_step, mod) {
  mod.doc() = "The compiled midpoint Moreau contact step (moreau_sim/compiled.py).";
#ifdef __GLIBC__
  // A step allocates its dense matrices afresh (M, M^-1, W, G: nv^2, nv m, m^2 doubles) and frees them. glibc's
  // threshold for serving an allocation by mmap follows the largest block freed so far, so one of 8 MB (a 1000-bead
  // column's M) can go to mmap at every step and fault its pages in anew (a third of that step). Fixed at glibc's
  // largest, 32 MB, and the heap kept up to 128 MB, blocks up to 32 MB are reused from the heap.
  mallopt(M_MMAP_THRESHOLD, 32 * 1024 * 1024);
  mallopt(M_TRIM_THRESHOLD, 128 * 1024 * 1024);
#endif
  nb::enum_<Outcome>(mod, "Outcome", "What a compiled step did: FLIGHT, CONTACT, or FALLBACK (the Python step takes it)")
      .value("FLIGHT", Outcome::FLIGHT)
      .value("CONTACT", Outcome::CONTACT)
      .value("FALLBACK", Outcome::FALLBACK);
  nb::enum_<Projection>(mod, "Projection", "How the projection was solved (qp.QPResult.status)")
      .value("ADMISSIBLE", Projection::ADMISSIBLE)
      .value("ACTIVE_SET", Projection::ACTIVE_SET);
  nb::class_<StepOut>(mod, "StepOut", "One compiled step (src/step.cpp StepOut): its arrays by layout()")
      .def_ro("outcome", &StepOut::outcome)
      .def_ro("reason", &StepOut::reason)
      .def_ro("m", &StepOut::m)
      // views of the two buffers (filled at the first read; the StepOut kept alive by them), not copies: a read
      // costs no copy of the buffer
      .def_prop_ro("floats", [](StepOut &o) -> VectorXd & { o.pack(); return o.floats; }, nb::rv_policy::reference_internal)
      .def_prop_ro("ints", [](StepOut &o) -> VectorXl & { o.pack(); return o.ints; }, nb::rv_policy::reference_internal)
      // M (nv, nv, 'C') and W (nv, m, 'F'): views of their own buffers (layout's buffers 2, 3), already shaped
      .def_prop_ro("M", [](StepOut &o) -> decltype(StepOut::M) & { return o.dense_M(); }, nb::rv_policy::reference_internal)
      .def_prop_ro("W", [](StepOut &o) -> const MatrixXd & { return o.W; }, nb::rv_policy::reference_internal)
      .def("layout", &StepOut::layout, "(name, buffer: 0 floats 1 ints 2 M 3 W, offset, rows, cols (0: a vector), order 'C'/'F') per array")
      .def_ro("projection", &StepOut::projection)
      .def_ro("contact_work", &StepOut::contact_work)
      .def_ro("correction_energy", &StepOut::correction_energy)
      .def_ro("obstacle_work", &StepOut::obstacle_work)
      .def_ro("drive_work_free", &StepOut::drive_work_free)
      .def_ro("paid", &StepOut::paid);
  nb::class_<Stepper>(mod, "Stepper")
      .def(nb::init<nb::object, const Forest::TreeArgs &, std::vector<int64_t>, std::vector<int64_t>, nb::object,
                    nb::object, std::vector<MatrixXd>, std::vector<int>,
                    std::vector<Vec3>, std::vector<double>, Eigen::Matrix<int64_t, Eigen::Dynamic, Eigen::Dynamic>,
                    double, double, double, int, bool, bool, bool, bool, bool,
                    const std::map<std::string, double> &, MatrixXd>())
      .def("step", &Stepper::step, nb::arg("q"), nb::arg("u"), nb::arg("h"), nb::arg("e"),
           nb::arg("tau") = VectorXd(), nb::arg("t") = std::numeric_limits<double>::quiet_NaN())
      .def("rheonomic", &Stepper::rheonomic, nb::arg("moving"), nb::arg("driven"))
      .def_prop_ro("constants", &Stepper::constants)
      .def("boxes", &Stepper::boxes)
      .def("broad", &Stepper::broad)
      .def("table", &Stepper::table)
      .def("gap_reach", &Stepper::gap_reach, nb::arg("reach"), nb::arg("margin"))
      .def("geometry_gaps", &Stepper::geometry_gaps_at, nb::arg("q"))
      .def_prop_ro("candidates", &Stepper::last_candidates)
      .def_prop_rw("warm", &Stepper::warm, &Stepper::set_warm)
      .def_prop_rw("active", &Stepper::active, &Stepper::set_active);
  bind_run(mod);
  bind_events(mod);
  // The GeometryModel of these geometries and no pair (a scene without a pair list: the Stepper's placements, Stepper::
  // table), made in one pass: pinocchio's addGeometryObject resizes a G x G pair map at each call (cubic in
  // geometries: 17 s at 3000); its pair map stays empty, so no pair may be added to it
  mod.def("geometry_model", [](std::vector<nb::object> objects) {
    pinocchio::GeometryModel gm;
    gm.geometryObjects.reserve(objects.size());
    for (const nb::object &o : objects)
      gm.geometryObjects.push_back(extract_ref<pinocchio::GeometryObject>(o, "pinocchio.GeometryObject"));
    gm.ngeoms = gm.geometryObjects.size();
    const bp::object out(gm);  // boost.python's pin.GeometryModel (a copy)
    return nb::borrow<nb::object>(out.ptr());
  });
  mod.def("reset_guesses", &reset_guesses, nb::arg("geom_data").none(), nb::arg("requests"), nb::arg("results"),
          "Every cached GJK guess and support hint of these coal objects back to a new object's (data.Data.reset)");
  // the names the constants dict must hold (moreau_sim/compiled.py CONSTANTS), and a dict as the step reads it
  mod.def("constant_names", []() { return Constants::keys(); });
  mod.def("read_constants", [](const std::map<std::string, double> &d) { return Constants::from(d).as_dict(); },
          nb::arg("constants"));
  // the projection alone (tests/test_compiled.py holds it bit-identical to qp.solve): (Projection, v, lam), or
  // (None, reason, None) where qp.solve goes on to piqp
  mod.def("project", [](const MatrixXd &W, const VectorXd &v0, const VectorXd &b, const MatrixXd &Minv,
                        const std::map<std::string, double> &constants) {
    if (W.rows() != v0.size() || b.size() != W.cols() || Minv.rows() != W.rows() || Minv.cols() != W.rows())
      throw nb::value_error("W (nv, m), v0 (nv,), b (m,), Minv (nv, nv) expected");
    const Constants C = Constants::from(constants);
    try {
      Solved s = project(C, W, v0, b, Minv);
      return nb::make_tuple(s.status, s.v, s.lam);
    } catch (const Fallback &f) {
      return nb::make_tuple(nb::none(), f.why, nb::none());
    }
  }, nb::arg("W"), nb::arg("v0"), nb::arg("b"), nb::arg("Minv"), nb::arg("constants"));
  // the kernels of docs/theory.md §2.8 alone (tests/test_compiled.py holds them bit-identical to sums.ordered and
  // qp._lu_solve): ordered(A, X) = A @ X summed as odot sums, lu_solve(A, rhs) = x, or None where it fails
  mod.def("ordered", [](const MatrixXd &A, const MatrixXd &X) {
    if (A.cols() != X.rows()) throw nb::value_error("A (r, n), X (n, c) expected");
    MatrixXd Y;
    omatmul(A, X, Y);
    return Y;
  }, nb::arg("A"), nb::arg("X"));
  mod.def("lu_solve", [](const MatrixXd &A, const VectorXd &rhs) -> nb::object {
    if (A.rows() != A.cols() || A.rows() != rhs.size()) throw nb::value_error("A (n, n), rhs (n,) expected");
    VectorXd x;
    if (!lu_solve(A, rhs, x)) return nb::none();
    return nb::cast(x);
  }, nb::arg("A"), nb::arg("rhs"));
  // band_lu_solve on a clean A (finite, no -0.0: a contact-space G) and the rows and columns sel of it (ascending), as
  // the active set solves G_AA: x, or None where it fails (tests/test_compiled.py holds it bit-identical to
  // qp._lu_solve of A[sel][:, sel])
  mod.def("lu_solve_band", [](const MatrixXd &A, const VectorXd &rhs, std::vector<Eigen::Index> sel) -> nb::object {
    if (A.rows() != A.cols() || (Eigen::Index)sel.size() != rhs.size()) throw nb::value_error("A (n, n), rhs (len(sel),) expected");
    if (!clean(A)) throw nb::value_error("A: finite, without -0.0 expected");
    std::vector<Eigen::Index> pos((size_t)A.rows(), -1);
    for (size_t i = 0; i < sel.size(); ++i) {
      if (sel[i] < 0 || sel[i] >= A.rows() || (i && sel[i] <= sel[i - 1])) throw nb::value_error("sel: ascending rows of A");
      pos[(size_t)sel[i]] = (Eigen::Index)i;
    }
    if (sel.empty()) return nb::cast(VectorXd(0));
    GInfo gi;
    gi.set(A);
    BandLU w;
    VectorXd x;
    if (!band_lu_solve(w, gi, sel, pos.data(), rhs, x)) return nb::none();
    return nb::cast(x);
  }, nb::arg("A"), nb::arg("rhs"), nb::arg("sel"));
  // constraints.distinct's columns kept (Stepper::distinct; tests/test_compiled.py holds them equal to Python's)
  mod.def("distinct_rows", [](const MatrixXd &W, double rel) { return distinct_rows(W, rel, nullptr); }, nb::arg("W"), nb::arg("rel"));
  // the factor prefix kept (band_lu_solve's comment; sparse: sub_lu_solve's, sparse_lu_factor): on one BandLU (or
  // SparseCache), the rows and columns `before` of a clean A (a right-hand side of ones), then `sel` with rhs: (x or
  // None, the elimination steps the second solve took from the first's factor) (tests/test_compiled.py holds x
  // bit-identical to qp._lu_solve of A[sel][:, sel])
  mod.def("lu_solve_after", [](const MatrixXd &A, std::vector<Eigen::Index> before, std::vector<Eigen::Index> sel,
                               const VectorXd &rhs, bool sparse) -> nb::object {
    if (A.rows() != A.cols() || (Eigen::Index)sel.size() != rhs.size()) throw nb::value_error("A (n, n), rhs (len(sel),) expected");
    if (!clean(A)) throw nb::value_error("A: finite, without -0.0 expected");
    GInfo gi;
    gi.set(A);
    BandLU w;
    SparseCache sc;
    VectorXd x;
    for (const auto *s : {&before, &sel}) {
      std::vector<Eigen::Index> pos((size_t)A.rows(), -1);
      for (size_t i = 0; i < s->size(); ++i) {
        if ((*s)[i] < 0 || (*s)[i] >= A.rows() || (i && (*s)[i] <= (*s)[i - 1])) throw nb::value_error("before, sel: ascending rows of A");
        pos[(size_t)(*s)[i]] = (Eigen::Index)i;
      }
      if (s->empty()) throw nb::value_error("before, sel: not empty");
      const VectorXd b = s == &sel ? rhs : VectorXd::Ones((Eigen::Index)s->size()).eval();
      const bool ok = sparse ? sub_lu_solve(sc, gi, *s, pos.data(), b, x) : band_lu_solve(w, gi, *s, pos.data(), b, x);
      if (s == &sel) return nb::make_tuple(ok ? nb::cast(x) : nb::none(), sparse ? sc.f[sc.last].reused : w.reused);
    }
    return nb::none();
  }, nb::arg("A"), nb::arg("before"), nb::arg("sel"), nb::arg("rhs"), nb::kw_only(), nb::arg("sparse") = false);
  // how this build does floating point (docs/theory.md §2.8): the options CMakeLists.txt compiled it with, whether
  // the target has FMA instructions, FLT_EVAL_METHOD (0: every double operation rounds to double), and a probe
  // a * b + c on run-time values, contracted to one fused rounding only if the build contracts
  mod.def("fp_build", []() {
    std::map<std::string, std::string> d;
    d["options"] = MOREAU_STEP_FP_OPTIONS;
#ifdef __FMA__
    d["fma_instructions"] = "yes";
#else
    d["fma_instructions"] = "no";
#endif
    d["flt_eval_method"] = std::to_string(FLT_EVAL_METHOD);
    d["compiler"] = __VERSION__;
    return d;
  });
  mod.def("fp_probe", [](double a, double b, double c) { return a * b + c; }, nb::arg("a"), nb::arg("b"), nb::arg("c"));
  bind_adaptive(mod);
  bind_impact(mod);
  bind_locate(mod);
  bind_phase(mod);
}
