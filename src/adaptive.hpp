// The adaptive integrator's samples on its dense output (moreau_sim/compiled_events.py; docs/theory.md §8): the
// quintic Hermite interpolant of a step's ends evaluated at the output instants the step covers, and what each
// sample records (src/forest.hpp: kinetic and potential energy, the pairs' distances), in one call for all the
// samples of a step, operation by operation as adaptive.AdaptiveRun._segment and _dense, then
// recording.Recorder.sample compute them (sums in index order: docs/theory.md §2.8), for configurations in a
// vector space (no joint with nq != nv; a Lie group stays with the Python dense output). And the gaps of points on
// static planes (gaps.Gaps.features's "point_plane" kind: vertices and spheres on half-spaces) and of sphere pairs
// ("sphere_sphere") with their rows, drift and rates, operation by operation as gaps.py and
// kinematics.Kinematics.point compute them (FeatureGaps). #included by step.cpp after run.cpp (ForestFigures).

#include <pinocchio/algorithm/jacobian.hpp>

#include <cmath>

class DenseSampler {
 public:
  using Rows = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  // stepper: the run's compiled Stepper (its GeometryData is the Python run's data.geom); trees, tree_of_joint,
  // local_joint: as Runner's (src/forest.hpp); basis: hermite.QUINTIC (6 x 6), row k the power coefficients of
  // the basis function of Hermite datum k
  DenseSampler(nb::object stepper, const ForestFigures::TreeArgs &trees, std::vector<int64_t> tree_of_joint,
               std::vector<int64_t> local_joint, std::vector<std::vector<double>> basis)
      : py_stepper_(stepper),
        forest_(nb::cast<Stepper &>(stepper), trees, std::move(tree_of_joint), std::move(local_joint)) {
    if (basis.size() != 6) throw nb::value_error("basis: 6 x 6 expected");
    for (int k = 0; k < 6; ++k) {
      if (basis[k].size() != 6) throw nb::value_error("basis: 6 x 6 expected");
      for (int i = 0; i < 6; ++i) B_[k][i] = basis[k][i];
    }
  }

  // The samples at the instants `grid` [s] of the step from (t0, q0, u0, a0) to (t1, q1, u1, a1) (a: the
  // accelerations at the ends): (q (n, nq), u (n, nv), kinetic energy (n,) [J], potential energy (n,) [J], the
  // pairs' distances (n, pairs) [m], NaN where coal's query failed), each as AdaptiveRun._segment's dense(t) and
  // Recorder.sample give it
  std::tuple<Rows, Rows, VectorXd, VectorXd, Rows> samples(double t0, const VectorXd &q0, const VectorXd &u0,
                                                            const VectorXd &a0, double t1, const VectorXd &q1,
                                                            const VectorXd &u1, const VectorXd &a1,
                                                            const VectorXd &grid) {
    const Eigen::Index nv = u0.size(), n = grid.size();
    if (q0.size() != nv || q1.size() != nv || u1.size() != nv || a0.size() != nv || a1.size() != nv)
      throw nb::value_error("q0, u0, a0, q1, u1, a1: (nv,) each expected (a vector space: nq = nv)");
    const double H = t1 - t0;
    Rows Q(n, nv), U(n, nv), G(n, (Eigen::Index)forest_.pairs());
    VectorXd T(n), V(n), q(nv), u(nv);
    Rows p;  // the interpolant's power coefficients (6, nv), built on first use (adaptive._poly)
    for (Eigen::Index i = 0; i < n; ++i) {
      const double tg = grid[i];
      if (tg >= t1) {
        q = q1, u = u1;
      } else if (H > 0) {
        if (p.size() == 0) p = poly(H, q0, u0, a0, q1, u1, a1);
        double tau = (tg - t0) / H;  // min(max(tau, 0.0), 1.0) as Python's min and max pick
        tau = 0.0 > tau ? 0.0 : tau;
        tau = 1.0 < tau ? 1.0 : tau;
        for (Eigen::Index c = 0; c < nv; ++c) {
          double y = p(5, c), s = 5.0 * p(5, c);  // adaptive._polyval, _polyslope (Horner)
          for (int k = 4; k >= 0; --k) y = y * tau + p(k, c);
          for (int k = 4; k >= 1; --k) s = s * tau + (double)k * p(k, c);
          q[c] = q0[c] + y, u[c] = s / H;
        }
      } else {
        q = q0, u = u0;
      }
      Q.row(i) = q.transpose(), U.row(i) = u.transpose();
      T[i] = forest_.kinetic(q, u), V[i] = forest_.potential(q);
      if (G.cols()) forest_.gaps(q, G.row(i).data());
    }
    return {std::move(Q), std::move(U), std::move(T), std::move(V), std::move(G)};
  }

  // What a sample records of the given states (Q (n, nq), U (n, nv)): (kinetic energy (n,) [J], potential energy
  // (n,) [J], the pairs' distances (n, pairs) [m], NaN where coal's query failed), as samples() records its own and
  // Recorder.sample records a state (the event-driven integrator's samples, whose states scipy's dense output gives;
  // any configuration space: no interpolation here)
  std::tuple<VectorXd, VectorXd, Rows> figures(const Rows &Q, const Rows &U) {
    const Eigen::Index n = Q.rows();
    if (U.rows() != n) throw nb::value_error("Q, U: as many rows expected");
    VectorXd T(n), V(n), q, u;
    Rows G(n, (Eigen::Index)forest_.pairs());
    for (Eigen::Index i = 0; i < n; ++i) {
      q = Q.row(i).transpose(), u = U.row(i).transpose();
      T[i] = forest_.kinetic(q, u), V[i] = forest_.potential(q);
      if (G.cols()) forest_.gaps(q, G.row(i).data());
    }
    return {std::move(T), std::move(V), std::move(G)};
  }

 private:
  nb::object py_stepper_;  // keeps the Stepper alive
  ForestFigures forest_;
  double B_[6][6];

  // adaptive._poly of the Hermite data (0, H u0, H^2 a0, q1 - q0, H u1, H^2 a1): QUINTIC.T @ coef summed in index
  // order from its first product, then + 0.0 (sums.ordered)
  Rows poly(double H, const VectorXd &q0, const VectorXd &u0, const VectorXd &a0, const VectorXd &q1,
            const VectorXd &u1, const VectorXd &a1) const {
    const Eigen::Index nv = u0.size();
    const double HH = H * H;
    Rows coef(6, nv);
    coef.row(0).setZero();
    for (Eigen::Index c = 0; c < nv; ++c) {
      coef(1, c) = H * u0[c], coef(2, c) = HH * a0[c], coef(3, c) = q1[c] - q0[c];
      coef(4, c) = H * u1[c], coef(5, c) = HH * a1[c];
    }
    Rows p(6, nv);
    for (int i = 0; i < 6; ++i)
      for (Eigen::Index c = 0; c < nv; ++c) {
        double s = B_[0][i] * coef(0, c);
        for (int k = 1; k < 6; ++k) s = s + B_[k][i] * coef(k, c);
        p(i, c) = s + 0.0;
      }
    return p;
  }
};

// gaps.Gaps.features on a model whose features are all points on static planes (kind "point_plane": the point p in
// joint j's frame, the plane n' x = d in the world) or pairs of spheres (kind "sphere_sphere": the centres p in joint
// j's frame and p_b in joint j_b's, radii r and r_b), on the run's own Pinocchio Data (data.pin, left as the Python
// features leave it), operation by operation as gaps.py and kinematics.Kinematics.point compute them
class FeatureGaps {
 public:
  using Rows = DenseSampler::Rows;
  enum Kind : int64_t { POINT_PLANE = 0, SPHERE_SPHERE = 1 };
  // kind, joint, joint_b (k,); p, n, p_b (k, 3); d, r, r_b (k,): the features (compiled_events.feature_gaps); mask:
  // model.support_mask (njoints, nv)
  FeatureGaps(nb::object model, nb::object data, std::vector<int64_t> kind, std::vector<int64_t> joint,
              std::vector<int64_t> joint_b, Rows p, Rows n, Rows p_b, std::vector<double> d, std::vector<double> r,
              std::vector<double> r_b, Rows mask)
      : py_model_(model), py_data_(data), model_(extract_ref<pinocchio::Model>(model, "pinocchio.Model")),
        data_(extract_ref<pinocchio::Data>(data, "pinocchio.Data")), kind_(std::move(kind)), joint_(std::move(joint)),
        joint_b_(std::move(joint_b)), p_(std::move(p)), n_(std::move(n)), p_b_(std::move(p_b)), d_(std::move(d)),
        r_(std::move(r)), r_b_(std::move(r_b)), mask_(std::move(mask)), zero_(VectorXd::Zero(model_.nv)) {
    const size_t k = joint_.size();
    if (kind_.size() != k || joint_b_.size() != k || (size_t)p_.rows() != k || (size_t)n_.rows() != k ||
        (size_t)p_b_.rows() != k || d_.size() != k || r_.size() != k || r_b_.size() != k || p_.cols() != 3 ||
        n_.cols() != 3 || p_b_.cols() != 3)
      throw nb::value_error("kind, joint, joint_b (k,), p, n, p_b (k, 3), d, r, r_b (k,) expected");
    for (size_t i = 0; i < k; ++i) {
      if (kind_[i] != POINT_PLANE && kind_[i] != SPHERE_SPHERE) throw nb::value_error("kind: 0 or 1 expected");
      if (joint_[i] < 0 || joint_[i] >= model_.njoints || joint_b_[i] < 0 || joint_b_[i] >= model_.njoints)
        throw nb::value_error("joint index out of range");
    }
    if (mask_.rows() != model_.njoints || mask_.cols() != model_.nv) throw nb::value_error("mask (njoints, nv)");
  }

  // (g (k,), W (nv, k), drift (k,), gamma (k,)) of the features idx at (q, u) as Gaps.features gives them (without
  // rows: W, drift, gamma zeros)
  std::tuple<VectorXd, Rows, VectorXd, VectorXd> features(const VectorXd &q, const VectorXd &u,
                                                          const std::vector<int64_t> &idx, bool rows) {
    const Eigen::Index nv = model_.nv, k = (Eigen::Index)idx.size();
    if (q.size() != model_.nq || u.size() != nv) throw nb::value_error("q (nq,), u (nv,) expected");
    for (auto i : idx)
      if (i < 0 || i >= (int64_t)joint_.size()) throw nb::value_error("feature index out of range");
    if (rows) pinocchio::computeJointJacobians(model_, data_, q);
    pinocchio::forwardKinematics(model_, data_, q, u, zero_);
    VectorXd g(k), drift = VectorXd::Zero(k), gamma = VectorXd::Zero(k);
    Rows W = Rows::Zero(nv, k);
    Point a(nv), b(nv);
    Eigen::Matrix<double, 3, Eigen::Dynamic> Jrel(3, nv);
    for (Eigen::Index col = 0; col < k; ++col) {
      const auto i = (size_t)idx[(size_t)col];
      point(joint_[i], p_.row((Eigen::Index)i).data(), rows, a);
      double n[3], curv = 0.0;
      const double *arel = a.acc;
      double ar[3];
      if (kind_[i] == POINT_PLANE) {
        for (int r = 0; r < 3; ++r) n[r] = n_((Eigen::Index)i, r);
        g[col] = dot3(n, a.p) - d_[i];
        if (rows) Jrel = a.J;
      } else {  // sphere_sphere: dv = pa - pb, dist = sqrt(dot3(dv, dv)), n = dv / dist
        point(joint_b_[i], p_b_.row((Eigen::Index)i).data(), rows, b);
        double dv[3], vrel[3];
        for (int r = 0; r < 3; ++r) dv[r] = a.p[r] - b.p[r];
        const double dist = std::sqrt(dot3(dv, dv));
        for (int r = 0; r < 3; ++r) n[r] = dv[r] / dist;
        g[col] = (dist - r_[i]) - r_b_[i];
        for (int r = 0; r < 3; ++r) vrel[r] = a.vel[r] - b.vel[r], ar[r] = a.acc[r] - b.acc[r];
        arel = ar;
        if (rows) {
          Jrel = a.J - b.J;
          curv = (dot3(vrel, vrel) - py_square(dot3(n, vrel))) / dist;  // (... - dot3(n, vrel) ** 2) / dist
        }
      }
      if (rows) {
        drift[col] = dot3(n, arel) + curv;
        for (Eigen::Index c = 0; c < nv; ++c)  // ordered(n, Jrel)
          W(c, col) = n[0] * Jrel(0, c) + n[1] * Jrel(1, c) + n[2] * Jrel(2, c) + 0.0;
      }
    }
    if (rows)  // gamma = ordered(W.T, u): each sum in index order from its first product, then + 0.0
      for (Eigen::Index col = 0; col < k; ++col) {
        double s = nv ? W(0, col) * u[0] : 0.0;
        for (Eigen::Index c = 1; c < nv; ++c) s = s + W(c, col) * u[c];
        gamma[col] = s + 0.0;
      }
    return {std::move(g), std::move(W), std::move(drift), std::move(gamma)};
  }

  // AdaptiveRun._end in free flight (no persistent set) on the features idx: (a, g, gamma, gdd) with a the free
  // accelerations (event_rules.dynamics: ABA on data.pin, first) and gdd = ordered(W.T, a) + drift
  std::tuple<VectorXd, VectorXd, VectorXd, VectorXd> end(const VectorXd &q, const VectorXd &u,
                                                         const std::vector<int64_t> &idx) {
    if (q.size() != model_.nq || u.size() != model_.nv) throw nb::value_error("q (nq,), u (nv,) expected");
    VectorXd a = pinocchio::aba(model_, data_, q, u, zero_);
    auto [g, W, drift, gamma] = features(q, u, idx, true);
    const Eigen::Index nv = model_.nv, k = g.size();
    VectorXd gdd(k);
    for (Eigen::Index col = 0; col < k; ++col) {
      double s = nv ? W(0, col) * a[0] : 0.0;
      for (Eigen::Index c = 1; c < nv; ++c) s = s + W(c, col) * a[c];
      gdd[col] = (s + 0.0) + drift[col];
    }
    return {std::move(a), std::move(g), std::move(gamma), std::move(gdd)};
  }

 private:
  nb::object py_model_, py_data_;  // keep the Python model and data (and so the C++ ones) alive
  const pinocchio::Model &model_;
  pinocchio::Data &data_;
  std::vector<int64_t> kind_, joint_, joint_b_;
  Rows p_, n_, p_b_;
  std::vector<double> d_, r_, r_b_;
  Rows mask_;
  VectorXd zero_;

  // Kinematics.point of a point fixed in a joint's frame: world position, velocity, bias acceleration, Jacobian
  struct Point {
    explicit Point(Eigen::Index nv) : J(3, nv) {}
    double p[3], vel[3], acc[3];
    Eigen::Matrix<double, 3, Eigen::Dynamic> J;
  };

  void point(int64_t j, const double *pl, bool rows, Point &out) const {
    const Eigen::Index nv = model_.nv;
    if (j == 0) {  // the world's point: p, at rest
      for (int r = 0; r < 3; ++r) out.p[r] = pl[r], out.vel[r] = 0.0, out.acc[r] = 0.0;
      out.J.setZero();
      return;
    }
    // (R, t, w, v, a_ang, a_lin) of the joint, cross and dots in Python's order
    const auto &M = data_.oMi[(size_t)j];
    const auto &R = M.rotation();
    const auto &t = M.translation();
    const Eigen::Vector3d w = data_.v[(size_t)j].angular(), v_lin = data_.v[(size_t)j].linear();
    const Eigen::Vector3d a_ang = data_.a[(size_t)j].angular(), a_lin = data_.a[(size_t)j].linear();
    double wp[3], vl[3], awp[3], wvl[3], al[3];
    cross(w.data(), pl, wp);
    for (int r = 0; r < 3; ++r) vl[r] = v_lin[r] + wp[r];
    for (int r = 0; r < 3; ++r) out.p[r] = (R(r, 0) * pl[0] + R(r, 1) * pl[1] + R(r, 2) * pl[2] + 0.0) + t[r];
    for (int r = 0; r < 3; ++r) out.vel[r] = R(r, 0) * vl[0] + R(r, 1) * vl[1] + R(r, 2) * vl[2] + 0.0;
    cross(a_ang.data(), pl, awp);
    cross(w.data(), vl, wvl);
    for (int r = 0; r < 3; ++r) al[r] = (a_lin[r] + awp[r]) + wvl[r];
    for (int r = 0; r < 3; ++r) out.acc[r] = R(r, 0) * al[0] + R(r, 1) * al[1] + R(r, 2) * al[2] + 0.0;
    if (rows) {  // (J[:3] - ordered(skew(p), J[3:])) * mask[j]
      const double *pw = out.p;
      const double S[3][3] = {{0.0, -pw[2], pw[1]}, {pw[2], 0.0, -pw[0]}, {-pw[1], pw[0], 0.0}};
      const auto &J = data_.J;
      for (Eigen::Index c = 0; c < nv; ++c)
        for (int r = 0; r < 3; ++r) {
          const double sj = S[r][0] * J(3, c) + S[r][1] * J(4, c) + S[r][2] * J(5, c) + 0.0;
          out.J(r, c) = (J(r, c) - sj) * mask_(j, c);
        }
    }
  }

  static double dot3(const double *a, const double *b) {  // sums.dot3
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + 0.0;
  }

  static void cross(const double *a, const double *b, double *out) {  // kinematics.cross
    out[0] = a[1] * b[2] - a[2] * b[1], out[1] = a[2] * b[0] - a[0] * b[2], out[2] = a[0] * b[1] - a[1] * b[0];
  }

  // Python's float x ** 2: the C library's pow(|x|, 2.0) (CPython's float_pow), not folded into x * x by the
  // compiler (the exponent is read at run time)
  static double py_square(double x) {
    static volatile double two = 2.0;
    return std::pow(std::fabs(x), (double)two);
  }
};

inline void bind_adaptive(nb::module_ &mod) {
  nb::class_<DenseSampler>(mod, "DenseSampler",
                           "The adaptive integrator's samples on its dense output (src/adaptive.hpp)")
      .def(nb::init<nb::object, const ForestFigures::TreeArgs &, std::vector<int64_t>, std::vector<int64_t>,
                    std::vector<std::vector<double>>>(),
           nb::arg("stepper"), nb::arg("trees"), nb::arg("tree_of_joint"), nb::arg("local_joint"), nb::arg("basis"))
      .def("samples", &owned::Method<&DenseSampler::samples>::call, nb::arg("t0"), nb::arg("q0"), nb::arg("u0"),
           nb::arg("a0"), nb::arg("t1"), nb::arg("q1"), nb::arg("u1"), nb::arg("a1"), nb::arg("grid"),
           "(q, u, kinetic, potential, gaps) at the instants grid of the step t0 -> t1 (AdaptiveRun._segment)")
      .def("figures", &owned::Method<&DenseSampler::figures>::call, nb::arg("Q"), nb::arg("U"),
           "(kinetic, potential, gaps) of the states (Q, U), as Recorder.sample records them");
  nb::class_<FeatureGaps>(mod, "FeatureGaps",
                           "Gaps.features of points on static planes and of sphere pairs (src/adaptive.hpp)")
      .def(nb::init<nb::object, nb::object, std::vector<int64_t>, std::vector<int64_t>, std::vector<int64_t>,
                    FeatureGaps::Rows, FeatureGaps::Rows, FeatureGaps::Rows, std::vector<double>, std::vector<double>,
                    std::vector<double>, FeatureGaps::Rows>(),
           nb::arg("model"), nb::arg("data"), nb::arg("kind"), nb::arg("joint"), nb::arg("joint_b"), nb::arg("p"),
           nb::arg("n"), nb::arg("p_b"), nb::arg("d"), nb::arg("r"), nb::arg("r_b"), nb::arg("mask"))
      .def("features", &owned::Method<&FeatureGaps::features>::call, nb::arg("q"), nb::arg("u"), nb::arg("idx"),
           nb::arg("rows"),
           "(g, W, drift, gamma) of the features idx at (q, u) (gaps.Gaps.features)")
      .def("end", &owned::Method<&FeatureGaps::end>::call, nb::arg("q"), nb::arg("u"), nb::arg("idx"),
           "(a, g, gamma, gdd) of a free step end on the features idx (adaptive.AdaptiveRun._end)");
}
