// The impact at an event located by the adaptive and event-driven integrators, compiled (moreau_sim/compiled_events.py;
// docs/theory.md §7, §8): event_rules._impact's detection at q (Stepper::detect, contacts.detect's mirror), its
// constraints (constraints.assemble_constraints: M by CRBA, the rows, the closed joint limits, distinct rows), the
// Zeno rule on the approaching features and law.impact with Pinocchio's M^-1 (the projection: Stepper::project,
// qp.solve's mirror), operation by operation as Python computes them (docs/theory.md §2.8), so that the two give
// the same floats. Python calls it only where event_rules.missed_features has no candidate (no closed box-box vertex
// or edge, no closed cylinder feature: coal's rows are the rows); it hands back (outcome FALLBACK, coal's warm starts restored) a corner (the set-valued law stays in Python), more
// contacts than the compiled step takes, a projection its active set does not settle, and the events Python
// refuses (no closed contact, none approaching), which the Python impact then takes from the same state.
// #included by step.cpp after events.hpp (Stepper's friend: its detection, rows and projection).

class EventImpact {
 public:
  // stepper: the run's compiled Stepper (its Data and GeometryData are the run's); gap_tol [m]: a feature at most
  // this far is closed (event_rules.Rules.gap_tol); v_tol [m/s], g_zeno [m], v_zeno [m/s], dt_zeno [s]: event_rules'
  // V_TOL, G_ZENO, V_ZENO, DT_ZENO
  EventImpact(nb::object stepper, double gap_tol, double v_tol, double g_zeno, double v_zeno, double dt_zeno)
      : py_stepper_(stepper), s_(nb::cast<Stepper &>(stepper)), gap_tol_(gap_tol), v_tol_(v_tol), g_zeno_(g_zeno),
        v_zeno_(v_zeno), dt_zeno_(dt_zeno), zero_(VectorXd::Zero(s_.model_.nv)) {}

  // event_rules._impact at (t, q, u) with restitution e, the previous impact at last_impact [s], the features'
  // g [m], gamma [m/s], rows W (nv, features) and drift [m/s^2] at (q, u) (event_rules.features): (out, zeno,
  // speed, a_n). out: a StepOut (outcome CONTACT: u_next = u+, v, lam, P, gamma_minus, gamma_plus, M, W and the
  // contacts; contact_work = -(energy lost) [J]; or FALLBACK with its reason); zeno: the Zeno rule holds (e = 0
  // was applied); speed [m/s], a_n [m/s^2]: the approaching features' -gamma and free normal accelerations
  std::tuple<StepOut, bool, VectorXd, VectorXd> impact(const VectorXd &q, const VectorXd &u, double e, double t,
                                                       double last_impact, const VectorXd &g, const VectorXd &gamma,
                                                       const MatrixXd &Wf, const VectorXd &drift) {
    Stepper &s = s_;
    const Eigen::Index nv = s.model_.nv, nf = g.size();
    if (q.size() != s.model_.nq || u.size() != nv) throw nb::value_error("q, u: sizes nq, nv expected");
    if (gamma.size() != nf || drift.size() != nf || Wf.rows() != nv || Wf.cols() != nf)
      throw nb::value_error("g, gamma, drift (features,), W (nv, features) expected");
    StepOut out;
    VectorXd speed, a_n;
    bool zeno = false;
    try {
      if (!u.allFinite()) throw Fallback{"a non-finite velocity"};  // qp.solve's NON_FINITE_INPUT: Python raises it
      // contacts.detect at q (corners hand the event back: Stepper::vertex_contacts), then
      // constraints.assemble_constraints: M (fills the WORLD Jacobians), the closed limits, the rows, distinct rows
      std::vector<Found> found = s.detect(q, nullptr);
      warm_.clear();  // contacts.detect's data.warm_start_pairs: the pairs of its contacts
      for (const Found &f : found) warm_.push_back(f.pair);
      std::sort(warm_.begin(), warm_.end());
      warm_.erase(std::unique(warm_.begin(), warm_.end()), warm_.end());
      s.closed_limits(q, found);
      MatrixXd M = s.crba_world(q);
      MatrixXd W0 = s.contact_rows(found);
      const std::vector<int> keep = s.distinct(W0);
      const Eigen::Index m = (Eigen::Index)keep.size();
      if (m == 0) throw Fallback{"no closed contact"};  // Python raises it
      MatrixXd W(nv, m);
      std::vector<Found> con;
      for (Eigen::Index j = 0; j < m; ++j) W.col(j) = W0.col(keep[j]), con.push_back(found[keep[j]]);
      VectorXd gm = otimes_t(W, u);
      if (!(gm.array() < -v_tol_).any()) throw Fallback{"no closed contact approaches"};  // Python raises it
      // the Zeno rule on the approaching features (event_rules._impact): a_n = W_appr' ABA(q, u) + drift_appr
      std::vector<Eigen::Index> appr;
      for (Eigen::Index i = 0; i < nf; ++i)
        if (g[i] <= gap_tol_ && gamma[i] < -v_tol_) appr.push_back(i);
      const VectorXd a = s.aba(q, u, zero_);  // ABA on the forest (docs/theory.md §2.12)
      const Eigen::Index na = (Eigen::Index)appr.size();
      speed.resize(na), a_n.resize(na);
      bool low = true;
      for (Eigen::Index k = 0; k < na; ++k) {
        const Eigen::Index i = appr[(size_t)k];
        a_n[k] = (nv ? odot(Wf.col(i).data(), a.data(), nv) : 0.0) + drift[i];
        speed[k] = -gamma[i];
        const double es = e * speed[k];
        low = low && ((es * es < (-2.0 * a_n[k]) * g_zeno_) || (speed[k] < v_zeno_));
      }
      zeno = low || t - last_impact < dt_zeno_;
      const double e_used = zeno ? 0.0 : e;
      // law.impact (v0 = u-, b = 0) with Pinocchio's M^-1 (docs/theory.md §2.8)
      const MatrixXd Minv = s.minverse(q);
      Solved res = s.project(W, u, VectorXd::Zero(m), Minv);
      VectorXd u_plus = res.v - e_used * (u - res.v);  // law.outcome
      const VectorXd v_perp = u - res.v;
      VectorXd y(nv);  // sums.ordered(v_perp, M): y_j = sum_k v_perp_k M_kj
      for (Eigen::Index j = 0; j < nv; ++j) y[j] = odot(v_perp.data(), M.data() + j * nv, nv);
      const double loss = (0.5 * (1.0 - e_used * e_used)) * (nv ? odot(y.data(), v_perp.data(), nv) : 0.0);
      out.outcome = Outcome::CONTACT;
      out.q_next = q, out.u_free = u, out.v_free = u, out.b = VectorXd::Zero(m);
      out.gamma_minus = std::move(gm), out.gamma_plus = otimes_t(W, u_plus);
      out.P = (1.0 + e_used) * res.lam;
      out.u_next = std::move(u_plus);
      out.g.resize(m);
      out.point_a.resize(m, 3), out.point_b.resize(m, 3), out.normal.resize(m, 3);
      out.pair.resize(m), out.kind.resize(m), out.feature.resize(m), out.joint_a.resize(m), out.joint_b.resize(m);
      for (Eigen::Index i = 0; i < m; ++i) {
        out.g[i] = con[i].g;
        out.point_a.row(i) = con[i].pa.transpose(), out.point_b.row(i) = con[i].pb.transpose();
        out.normal.row(i) = con[i].n.transpose();
        out.pair[i] = con[i].pair, out.kind[i] = con[i].kind, out.feature[i] = con[i].feature;
        const auto jab = s.joints_of(con[i]);
        out.joint_a[i] = jab.first, out.joint_b[i] = jab.second;
      }
      out.v = std::move(res.v), out.lam = std::move(res.lam), out.W = std::move(W);
      out.set_M(M, s.blocks_);
      out.projection = res.status, out.contact_work = -loss, out.m = m;
    } catch (const Fallback &f) {
      s.restore_guesses();
      out = StepOut();
      out.outcome = Outcome::FALLBACK, out.reason = f.why;
      zeno = false, speed.resize(0), a_n.resize(0);
    }
    return {std::move(out), zeno, std::move(speed), std::move(a_n)};
  }

  // the pairs of the last detection's contacts (contacts.detect's data.warm_start_pairs)
  std::vector<int> warm() const { return warm_; }

 private:
  nb::object py_stepper_;  // keeps the Stepper alive
  Stepper &s_;
  double gap_tol_, v_tol_, g_zeno_, v_zeno_, dt_zeno_;
  VectorXd zero_;
  std::vector<int> warm_;
};

inline void bind_impact(nb::module_ &mod) {
  nb::class_<EventImpact>(mod, "EventImpact", "The impact at a located event (src/impact.hpp)")
      .def(nb::init<nb::object, double, double, double, double, double>(), nb::arg("stepper"), nb::arg("gap_tol"),
           nb::arg("v_tol"), nb::arg("g_zeno"), nb::arg("v_zeno"), nb::arg("dt_zeno"))
      .def("impact", &owned::Method<&EventImpact::impact>::call, nb::arg("q"), nb::arg("u"), nb::arg("e"),
           nb::arg("t"), nb::arg("last_impact"), nb::arg("g"), nb::arg("gamma"), nb::arg("W"), nb::arg("drift"),
           "(StepOut, zeno, speed, a_n): event_rules._impact at (t, q, u), or a FALLBACK StepOut (Python takes it)")
      .def_prop_ro("warm", &EventImpact::warm);
}
