// The adaptive integrator's step in free flight, in one call (moreau_sim/compiled_events.py; docs/theory.md §8):
// adaptive.AdaptiveRun.step's part between its phase's start and its bookkeeping, with no persistent set, on
// compiled features (src/adaptive.hpp FeatureGaps), in a vector space whose neutral configuration is 0: the step
// sizes tried until the error test passes (the extrapolated step, src/events.hpp), the step's end, the event
// location on it (src/locate.hpp) and the landing onto the event, operation by operation as Python computes them
// (docs/theory.md §2.8), so that a run gives the Python run's arrays bit for bit. Python keeps the decisions that
// follow (the samples, the state, the fall to fixed steps, the errors). #included by step.cpp after locate.hpp.

class PhaseStep {
 public:
  // Why step() returned (its first result; moreau_sim._step.PhaseStatus)
  enum class Status { ACCEPTED, LANDED, REFUSED, NONFINITE, LOCATE };

  // extrapolator, gaps, locator: the run's Extrapolator, FeatureGaps and EventLocator; rtol, atol, order: the
  // run's; h_min, safety, min_factor, land_iter, g_land: adaptive.H_MIN, SAFETY, MIN_FACTOR, LAND_ITER, G_LAND
  PhaseStep(nb::object extrapolator, nb::object gaps, nb::object locator, double rtol, double atol, int order,
            double h_min, double safety, double min_factor, int land_iter, double g_land)
      : py_ex_(extrapolator), py_gaps_(gaps), py_loc_(locator), ex_(nb::cast<Extrapolator &>(extrapolator)),
        gaps_(nb::cast<FeatureGaps &>(gaps)), loc_(nb::cast<EventLocator &>(locator)), rtol_(rtol), atol_(atol),
        exponent_(-1.0 / (double)(order - 1)), h_min_(h_min), safety_(safety), min_factor_(min_factor),
        land_iter_(land_iter), g_land_(g_land) {
    if (order < 2) throw nb::value_error("order >= 2 expected");
  }

  // From the state (t, q, u) with the step end e0 = (t0, q0, u0, g0, gamma0, gdd0) there (q0 = q, u0 = u), the
  // next step of size H at most (limit, t_end [s]: AdaptiveRun.step's) watching the features idx, the first nw by
  // their gaps. Returns (status, h, err, rejected, ends, landings, accepted, event):
  //  ACCEPTED: the step of size h, error estimate err, without an event; accepted = (t1, q1, u1, a1, g1, gamma1,
  //    gdd1), its end as AdaptiveRun._end gives it;
  //  LOCATE: as ACCEPTED, but the event location is Python's (the locator's status -1);
  //  LANDED: an event on the step of size h, event = (tau, kind: 0 a gap, 1 a return, k, hs, qs, us, as, gs,
  //    gammas, gdds): the landing's step of size hs and its end (AdaptiveRun._land, then _end at t + hs);
  //  REFUSED: no step size passed (h: the last one tried; the next was below h_min);
  //  NONFINITE: the error estimate of the step of size h is not finite.
  // rejected: the step sizes refused; ends: the step ends evaluated (event_rules' nfev); landings: the landing's
  // steps.
  nb::tuple step(double t, const VectorXd &q, const VectorXd &u, double H, double limit, double t_end, double t0,
                 const VectorXd &q0, const VectorXd &u0, const VectorXd &g0, const VectorXd &gamma0,
                 const VectorXd &gdd0, const std::vector<int64_t> &idx, int64_t nw) {
    const Eigen::Index nq = q.size(), nv = u.size();
    if (nq != nv || q0.size() != nq || u0.size() != nv)
      throw nb::value_error("q, u, q0, u0: (nv,) each expected (a vector space)");
    const VectorXd z0 = size(q, u);
    int rejected = 0, ends = 0, landings = 0;
    double h, err;
    VectorXd q1, u1;
    while (true) {
      h = H;  // min(H, limit, t_end - t) as Python's min picks
      if (limit < h) h = limit;
      if (t_end - t < h) h = t_end - t;
      VectorXd d;
      std::tie(q1, u1, d) = ex_.step(q, u, h);
      err = error(z0, q1, u1, d);
      if (!std::isfinite(err)) return result(Status::NONFINITE, h, err, rejected, ends, landings);
      if (err <= 1.0) break;
      ++rejected;
      const double f = safety_ * std::pow(err, exponent_);
      H = h * (min_factor_ < f ? f : min_factor_);  // max(MIN_FACTOR, f) as Python's max picks
      if (H < h_min_) return result(Status::REFUSED, h, err, rejected, ends, landings);
    }
    const bool last = h >= t_end - t;
    const double t1 = last ? t_end : t + h;
    auto [a1, g1, gamma1, gdd1] = gaps_.end(q1, u1, idx);
    ++ends;
    auto [status, tau, kind, k] = loc_.first(t0, g0, gamma0, gdd0, t1, g1, gamma1, gdd1, nw);
    if (status <= 0)
      return result(status < 0 ? Status::LOCATE : Status::ACCEPTED, h, err, rejected, ends, landings,
                    nb::make_tuple(t1, owned::array(std::move(q1)), owned::array(std::move(u1)),
                                   owned::array(std::move(a1)), owned::array(std::move(g1)),
                                   owned::array(std::move(gamma1)), owned::array(std::move(gdd1))));
    // AdaptiveRun._land: Newton on the gap of watched feature k (a gap event), one step onto a return
    double Hs = tau * h, hs = 0.0;
    VectorXd qs = q0, us = u0, as, gs, gams, gdds;
    bool have_end = false;
    const int iters = kind == 0 ? land_iter_ : 1;
    for (int it = 0; it < iters; ++it) {
      if (Hs <= 0.0) break;
      VectorXd d;
      hs = Hs;
      std::tie(qs, us, d) = ex_.step(q0, u0, Hs);
      ++landings;
      if (kind != 0) break;
      std::tie(as, gs, gams, gdds) = gaps_.end(qs, us, idx);
      have_end = true;
      const double g = gs[k], gam = gams[k];
      if (std::fabs(g) <= g_land_ || gam >= 0.0) break;
      Hs -= g / gam;
    }
    if (t_end - t < hs) hs = t_end - t;  // min(hs, t_end - t)
    if (!have_end) std::tie(as, gs, gams, gdds) = gaps_.end(qs, us, idx);
    ++ends;  // (AdaptiveRun._end counts the landed end, its values the landing's own or new)
    nb::object event = nb::make_tuple(tau, kind, k, hs, owned::array(std::move(qs)), owned::array(std::move(us)),
                                      owned::array(std::move(as)), owned::array(std::move(gs)),
                                      owned::array(std::move(gams)), owned::array(std::move(gdds)));
    return result(Status::LANDED, h, err, rejected, ends, landings, nb::none(), event);
  }

 private:
  nb::object py_ex_, py_gaps_, py_loc_;  // keep the objects below alive
  Extrapolator &ex_;
  FeatureGaps &gaps_;
  EventLocator &loc_;
  double rtol_, atol_, exponent_, h_min_, safety_, min_factor_;
  int land_iter_;
  double g_land_;

  // AdaptiveRun._size on a vector space with neutral 0: |(q, u)|
  static VectorXd size(const VectorXd &q, const VectorXd &u) {
    VectorXd z(q.size() + u.size());
    z << q.cwiseAbs(), u.cwiseAbs();
    return z;
  }

  // AdaptiveRun._error: the RMS of d / (atol + rtol max(z0, z1)), np.maximum's NaN kept, summed in index order
  double error(const VectorXd &z0, const VectorXd &q1, const VectorXd &u1, const VectorXd &d) const {
    const VectorXd z1 = size(q1, u1);
    const Eigen::Index n = d.size();
    if (n == 0) return std::nan("");
    double s = 0.0;
    for (Eigen::Index i = 0; i < n; ++i) {
      const double a = z0[i], b = z1[i];
      const double m = std::isnan(a) ? a : std::isnan(b) ? b : (a < b ? b : a);
      const double z = d[i] / (atol_ + rtol_ * m);
      s += z * z;
    }
    return std::sqrt((s + 0.0) / (double)n);
  }

  static nb::tuple result(Status status, double h, double err, int rejected, int ends, int landings,
                          nb::object accepted = nb::none(), nb::object event = nb::none()) {
    return nb::make_tuple(status, h, err, rejected, ends, landings, accepted, event);
  }
};

inline void bind_phase(nb::module_ &mod) {
  nb::enum_<PhaseStep::Status>(mod, "PhaseStatus", "Why PhaseStep.step returned (src/phase.hpp)")
      .value("ACCEPTED", PhaseStep::Status::ACCEPTED)
      .value("LANDED", PhaseStep::Status::LANDED)
      .value("REFUSED", PhaseStep::Status::REFUSED)
      .value("NONFINITE", PhaseStep::Status::NONFINITE)
      .value("LOCATE", PhaseStep::Status::LOCATE);
  nb::class_<PhaseStep>(mod, "PhaseStep", "The adaptive integrator's step in free flight in one call (src/phase.hpp)")
      .def(nb::init<nb::object, nb::object, nb::object, double, double, int, double, double, double, int, double>(),
           nb::arg("extrapolator"), nb::arg("gaps"), nb::arg("locator"), nb::arg("rtol"), nb::arg("atol"),
           nb::arg("order"), nb::arg("h_min"), nb::arg("safety"), nb::arg("min_factor"), nb::arg("land_iter"),
           nb::arg("g_land"))
      .def("step", &PhaseStep::step, nb::arg("t"), nb::arg("q"), nb::arg("u"), nb::arg("H"), nb::arg("limit"),
           nb::arg("t_end"), nb::arg("t0"), nb::arg("q0"), nb::arg("u0"), nb::arg("g0"), nb::arg("gamma0"),
           nb::arg("gdd0"), nb::arg("idx"), nb::arg("nw"),
           "(status, h, err, rejected, ends, landings, accepted, event): AdaptiveRun.step in free flight");
}
