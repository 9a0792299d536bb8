// The adaptive integrator's samples on its dense output (moreau_sim/compiled_events.py; docs/theory.md §8): the
// quintic Hermite interpolant of a step's ends evaluated at the output instants the step covers, and what each
// sample records (src/forest.hpp: kinetic and potential energy, the pairs' distances), in one call for all the
// samples of a step, operation by operation as adaptive.AdaptiveRun._segment and _dense, then
// recording.Recorder.sample compute them (sums in index order: docs/theory.md §2.8), for configurations in a
// vector space (no joint with nq != nv; a Lie group stays with the Python dense output). #included by step.cpp
// after run.cpp (ForestFigures).

class DenseSampler {
 public:
  using Rows = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  // stepper: the run's compiled Stepper (its GeometryData is the Python run's data.geom); trees, tree_of_joint,
  // local_joint: as Runner's (src/forest.hpp); basis: adaptive.QUINTIC (6 x 6), row k the power coefficients of
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

inline void bind_adaptive(nb::module_ &mod) {
  nb::class_<DenseSampler>(mod, "DenseSampler",
                           "The adaptive integrator's samples on its dense output (src/adaptive.hpp)")
      .def(nb::init<nb::object, const ForestFigures::TreeArgs &, std::vector<int64_t>, std::vector<int64_t>,
                    std::vector<std::vector<double>>>(),
           nb::arg("stepper"), nb::arg("trees"), nb::arg("tree_of_joint"), nb::arg("local_joint"), nb::arg("basis"))
      .def("samples", &DenseSampler::samples, nb::arg("t0"), nb::arg("q0"), nb::arg("u0"), nb::arg("a0"),
           nb::arg("t1"), nb::arg("q1"), nb::arg("u1"), nb::arg("a1"), nb::arg("grid"),
           "(q, u, kinetic, potential, gaps) at the instants grid of the step t0 -> t1 (AdaptiveRun._segment)");
}
