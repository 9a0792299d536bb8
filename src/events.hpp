// The adaptive integrator's extrapolated step between events, in free flight (moreau_sim/compiled_events.py;
// docs/theory.md §8): n = seq[j] symmetric midpoint steps of H/n, extrapolated in h^2, operation by operation as
// adaptive.AdaptiveRun._step and _midpoint compute it without a persistent set, so that the two give the same
// floats (docs/theory.md §2.8). #included by step.cpp (its helpers: extract_ref).

// One extrapolated step of a model (its own Pinocchio Data): step(q0, u0, H) = (q1, u1, d) as AdaptiveRun._step
class Extrapolator {
 public:
  // ratios[j][m - 1] = (seq[j] / seq[j - m])^2 - 1 (adaptive.AdaptiveRun.ratios); lie: a joint with nq != nv;
  // velocity_bias: the bias depends on u (the midpoint's fixed point is iterated to fixed_point (atol + rtol |u|),
  // iterations sweeps at most: stepper.midpoint_fixed_point)
  Extrapolator(nb::object model, std::vector<int> seq, std::vector<std::vector<double>> ratios, bool lie,
               bool velocity_bias, double rtol, double atol, double fixed_point, int iterations)
      : py_(model), model_(extract_ref<pinocchio::Model>(model, "pinocchio.Model")), data_(model_),
        seq_(std::move(seq)), ratios_(std::move(ratios)), lie_(lie), velocity_bias_(velocity_bias), rtol_(rtol),
        atol_(atol), fixed_point_(fixed_point), iterations_(iterations), zero_(VectorXd::Zero(model_.nv)) {
    if (seq_.empty() || ratios_.size() != seq_.size()) throw nb::value_error("seq and ratios: one entry per row");
    for (size_t j = 0; j < seq_.size(); ++j)
      if (ratios_[j].size() != j) throw nb::value_error("ratios[j]: j entries expected");
  }

  std::tuple<VectorXd, VectorXd, VectorXd> step(const VectorXd &q0, const VectorXd &u0, double H) {
    const Eigen::Index nv = model_.nv;
    if (q0.size() != model_.nq || u0.size() != nv) throw nb::value_error("q0 (nq,), u0 (nv,) expected");
    std::vector<std::vector<VectorXd>> rows;
    rows.reserve(seq_.size());
    VectorXd q, u, q_next, u_next;
    for (size_t j = 0; j < seq_.size(); ++j) {
      const int n = seq_[j];
      const double h = H / n;
      q = q0, u = u0;
      for (int i = 0; i < n; ++i) {
        midpoint(q, u, h, q_next, u_next);
        q.swap(q_next), u.swap(u_next);
      }
      std::vector<VectorXd> row;
      row.reserve(j + 1);
      VectorXd y(2 * nv);
      if (lie_)
        y.head(nv) = pinocchio::difference(model_, q0, q);
      else
        y.head(nv) = q - q0;
      y.tail(nv) = u;
      row.push_back(std::move(y));
      for (size_t m = 1; m <= j; ++m) {
        const double r = ratios_[j][m - 1];
        row.push_back(row[m - 1] + (row[m - 1] - rows[j - 1][m - 1]) / r);
      }
      rows.push_back(std::move(row));
    }
    const VectorXd &y = rows.back().back();
    VectorXd q1 = lie_ ? VectorXd(pinocchio::integrate(model_, q0, y.head(nv))) : VectorXd(q0 + y.head(nv));
    VectorXd d = rows.back().size() > 1 ? VectorXd(y - rows.back()[rows.back().size() - 2]) : VectorXd(y - y);
    return {std::move(q1), VectorXd(y.tail(nv)), std::move(d)};
  }

 private:
  nb::object py_;  // keeps the Python model (and so the C++ one) alive
  const pinocchio::Model &model_;
  pinocchio::Data data_;
  std::vector<int> seq_;
  std::vector<std::vector<double>> ratios_;
  bool lie_, velocity_bias_;
  double rtol_, atol_, fixed_point_;
  int iterations_;
  VectorXd zero_;

  const VectorXd &acc(const VectorXd &q, const VectorXd &v) { return pinocchio::aba(model_, data_, q, v, zero_); }

  // AdaptiveRun._midpoint without a persistent set: stepper.free_velocity's one ABA, or the fixed point
  void midpoint(const VectorXd &q, const VectorXd &u, double h, VectorXd &q1, VectorXd &u1) {
    const VectorXd q_m = pinocchio::integrate(model_, q, (0.5 * h) * u);
    u1 = u + h * acc(q_m, u);
    if (velocity_bias_) {  // stepper.midpoint_fixed_point
      const double tol = fixed_point_ * (atol_ + rtol_ * u.cwiseAbs().maxCoeff());
      for (int it = 0; it < iterations_; ++it) {
        const VectorXd ubar = 0.5 * (u + u1);
        VectorXd nxt = u + h * acc(q_m, ubar);
        const bool done = (nxt - u1).cwiseAbs().maxCoeff() <= tol;
        u1.swap(nxt);
        if (done) break;
      }
    }
    q1 = pinocchio::integrate(model_, q_m, (0.5 * h) * u1);
  }
};

inline void bind_events(nb::module_ &mod) {
  nb::class_<Extrapolator>(mod, "Extrapolator",
                           "The adaptive integrator's extrapolated step in free flight (src/events.hpp)")
      .def(nb::init<nb::object, std::vector<int>, std::vector<std::vector<double>>, bool, bool, double, double, double,
                    int>(),
           nb::arg("model"), nb::arg("seq"), nb::arg("ratios"), nb::arg("lie"), nb::arg("velocity_bias"),
           nb::arg("rtol"), nb::arg("atol"), nb::arg("fixed_point"), nb::arg("iterations"))
      .def("step", &owned::Method<&Extrapolator::step>::call, nb::arg("q0"), nb::arg("u0"), nb::arg("H"),
           "(q1, u1, error estimate) of the step of size H from (q0, u0) (adaptive.AdaptiveRun._step)");
}
