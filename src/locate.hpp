// The adaptive integrator's event location on a step in free flight, compiled (moreau_sim/compiled_events.py;
// docs/theory.md §8): adaptive.AdaptiveRun._first_event without a persistent set and without box features, operation
// by operation as Python computes it (docs/theory.md §2.8): the gaps' quintic Hermite polynomials at the check
// instants (sums.ordered), their first crossings, the roots by Brent's method as scipy.optimize.brentq takes them
// (its arithmetic in its order, xtol 1e-15, rtol 4 eps, 100 iterations), and the returns of the features within
// G_RES of contact (their rates' cubic Hermite below -2 V_TOL). #included by step.cpp after impact.hpp.

#include <cmath>

class EventLocator {
 public:
  // check: the check instants tau_p in [0, 1] (hermite.CHECK); check_basis: (points, 6) hermite.CHECK_BASIS;
  // quintic: (6, 6) hermite.QUINTIC; v_tol [m/s]: event_rules.V_TOL
  EventLocator(VectorXd check, MatrixXd check_basis, MatrixXd quintic, double v_tol)
      : check_(std::move(check)), basis_(std::move(check_basis)), quintic_(std::move(quintic)), v_tol_(v_tol) {
    if (basis_.rows() != check_.size() || basis_.cols() != 6 || quintic_.rows() != 6 || quintic_.cols() != 6 ||
        check_.size() < 2)
      throw nb::value_error("check (points,), check_basis (points, 6), quintic (6, 6) expected");
  }

  // The earliest event on the step from (t0, g0, gamma0, gdd0) to (t1, g1, gamma1, gdd1) of the features watched
  // by their gaps (the first nw) and by their return (the rest): (status, tau, kind, k); status 1: an event at tau
  // in [0, 1] of kind 0 (a gap closing) or 1 (a return) of feature k; 0: none; -1: Python must locate it (a root
  // Brent's method does not settle, a non-finite value: scipy raises there)
  std::tuple<int, double, int, int64_t> first(double t0, const VectorXd &g0, const VectorXd &gamma0,
                                              const VectorXd &gdd0, double t1, const VectorXd &g1,
                                              const VectorXd &gamma1, const VectorXd &gdd1, int64_t nw) {
    const Eigen::Index nf = g0.size(), P = check_.size();
    if (gamma0.size() != nf || gdd0.size() != nf || g1.size() != nf || gamma1.size() != nf || gdd1.size() != nf ||
        nw < 0 || nw > nf)
      throw nb::value_error("g, gamma, gdd (features,) at both ends, 0 <= nw <= features expected");
    const double H = t1 - t0, HH = H * H;
    bool found = false;
    double best = 0.0;
    int kind = 0;
    int64_t at = 0;
    bool failed = false;
    auto offer = [&](double tau, int kd, int64_t k) {
      if (!found || tau < best) found = true, best = tau, kind = kd, at = k;
    };
    if (nf) {
      // coef (6, features): g0, H gamma0, H^2 gdd0, g1, H gamma1, H^2 gdd1; G = ordered(check_basis, coef), its last
      // row g1
      std::vector<int> first_j((size_t)nw, -1);
      int j_min = -1;
      double c[6];
      for (Eigen::Index k = 0; k < nw; ++k) {
        coef(k, H, HH, g0, gamma0, gdd0, g1, gamma1, gdd1, c);
        for (Eigen::Index p = 0; p < P; ++p) {
          double G;
          if (p == P - 1) {
            G = g1[k];
          } else {
            G = basis_(p, 0) * c[0];
            for (int t = 1; t < 6; ++t) G = G + basis_(p, t) * c[t];
            G = G + 0.0;
          }
          if (G < 0.0) {
            first_j[(size_t)k] = (int)p;
            break;
          }
        }
        if (first_j[(size_t)k] >= 0 && (j_min < 0 || first_j[(size_t)k] < j_min)) j_min = first_j[(size_t)k];
      }
      if (j_min < 0) j_min = 0;
      for (Eigen::Index k = 0; k < nw && !failed; ++k) {
        const int j = first_j[(size_t)k];
        if (j < 0 || j > j_min) continue;
        coef(k, H, HH, g0, gamma0, gdd0, g1, gamma1, gdd1, c);
        double pk[6];  // adaptive._poly: ordered(QUINTIC.T, coef[:, k])
        for (int r = 0; r < 6; ++r) {
          double s = quintic_(0, r) * c[0];
          for (int t = 1; t < 6; ++t) s = s + quintic_(t, r) * c[t];
          pk[r] = s + 0.0;
        }
        auto f = [&](double x) {  // adaptive._polyval (Horner)
          double y = pk[5];
          for (int m = 4; m >= 0; --m) y = y * x + pk[m];
          return y;
        };
        double tau;
        if (!root(f, check_[j == 0 ? P - 1 : j - 1], check_[j], tau)) failed = true;
        else offer(tau, 0, k);
      }
      // a feature within G_RES of contact coming back: gamma below -2 V_TOL (cubic Hermite of gamma)
      for (Eigen::Index k = nw; k < nf && !failed; ++k) {
        const double two_v = 2.0 * v_tol_;
        const double gc0 = gamma0[k] + two_v, gc1 = H * gdd0[k], gc2 = gamma1[k] + two_v, gc3 = H * gdd1[k];
        auto fr = [&](double x) {  // AdaptiveRun._first_event's fr, Python's order (x ** 3: libm's pow)
          const double x3 = cube(x);
          return ((gc0 * ((1.0 - (3.0 * x) * x) + 2.0 * x3) + gc1 * ((x - (2.0 * x) * x) + x3)) +
                  gc2 * ((3.0 * x) * x - 2.0 * x3)) + gc3 * (x3 - x * x);
        };
        int j = -1;
        bool first_ok = false;
        for (Eigen::Index p = 0; p < P; ++p) {
          const double v = fr(check_[p]);
          if (p == 0) first_ok = v >= 0.0;
          else if (j < 0 && v < 0.0) j = (int)p;
        }
        if (j < 0 || !first_ok) continue;
        double tau;
        if (!root(fr, check_[j - 1], check_[j], tau)) failed = true;
        else offer(tau, 1, k);
      }
    }
    if (failed) return {-1, 0.0, 0, 0};
    return {found ? 1 : 0, best, kind, at};
  }

 private:
  VectorXd check_;
  MatrixXd basis_, quintic_;
  double v_tol_;

  static void coef(Eigen::Index k, double H, double HH, const VectorXd &g0, const VectorXd &gamma0,
                   const VectorXd &gdd0, const VectorXd &g1, const VectorXd &gamma1, const VectorXd &gdd1,
                   double *c) {
    c[0] = g0[k], c[1] = H * gamma0[k], c[2] = HH * gdd0[k], c[3] = g1[k], c[4] = H * gamma1[k], c[5] = HH * gdd1[k];
  }
  // x ** 3 as Python takes it for x >= 0 (float_pow: libm's pow(x, 3.0)), the exponent opaque to the compiler
  static double cube(double x) {
    static volatile double three = 3.0;
    return std::pow(x, (double)three);
  }
  // adaptive._root: lo if f(lo) <= 0, hi if f(hi) > 0, else Brent's method on [lo, hi] as scipy.optimize.brentq
  // runs it (xtol 1e-15, rtol 4 eps, at most 100 iterations); false where scipy would raise (no convergence, a NaN)
  template <class F> static bool root(F &&f, double lo, double hi, double &x) {
    const double flo = f(lo);
    if (std::isnan(flo)) return false;
    if (flo <= 0.0) return x = lo, true;
    const double fhi = f(hi);
    if (std::isnan(fhi)) return false;
    if (fhi > 0.0) return x = hi, true;
    return brent(f, lo, hi, 1e-15, 4.0 * DBL_EPSILON, 100, x);
  }
  // Brent's method (scipy/optimize/Zeros/brentq.c's arithmetic, in its order): a bracket [a, b] (fa, fb of opposite
  // signs), the last two estimates, inverse quadratic or secant steps when short enough, else bisection
  template <class F> static bool brent(F &&f, double a, double b, double xtol, double rtol, int iters, double &x) {
    double xp = a, xc = b, xb = 0.0, fb = 0.0, sp = 0.0, sc = 0.0;
    double fp = f(xp), fc = f(xc);
    if (std::isnan(fp) || std::isnan(fc) || fp * fc > 0) return false;
    if (fp == 0) return x = xp, true;
    if (fc == 0) return x = xc, true;
    for (int i = 0; i < iters; ++i) {
      if (fp * fc < 0) xb = xp, fb = fp, sp = sc = xc - xp;
      if (std::fabs(fb) < std::fabs(fc)) {  // the estimate nearest the root becomes current
        xp = xc, xc = xb, xb = xp;
        fp = fc, fc = fb, fb = fp;
      }
      const double tol = (xtol + rtol * std::fabs(xc)) / 2;
      const double half = (xb - xc) / 2;
      if (fc == 0 || std::fabs(half) < tol) return x = xc, true;
      if (std::fabs(sp) > tol && std::fabs(fc) < std::fabs(fp)) {
        double s;
        if (xp == xb) {
          s = -fc * (xc - xp) / (fc - fp);  // secant
        } else {
          const double dp = (fp - fc) / (xp - xc), db = (fb - fc) / (xb - xc);
          s = -fc * (fb * db - fp * dp) / (db * dp * (fb - fp));  // inverse quadratic
        }
        if (2 * std::fabs(s) < std::min(std::fabs(sp), 3 * std::fabs(half) - tol)) sp = sc, sc = s;
        else sp = sc = half;
      } else {
        sp = sc = half;
      }
      xp = xc, fp = fc;
      xc += std::fabs(sc) > tol ? sc : (half > 0 ? tol : -tol);
      fc = f(xc);
      if (std::isnan(fc)) return false;
    }
    return false;  // scipy raises: not converged
  }
};

inline void bind_locate(nb::module_ &mod) {
  nb::class_<EventLocator>(mod, "EventLocator", "The adaptive integrator's event location in free flight (src/locate.hpp)")
      .def(nb::init<VectorXd, MatrixXd, MatrixXd, double>(), nb::arg("check"), nb::arg("check_basis"),
           nb::arg("quintic"), nb::arg("v_tol"))
      .def("first", &EventLocator::first, nb::arg("t0"), nb::arg("g0"), nb::arg("gamma0"), nb::arg("gdd0"),
           nb::arg("t1"), nb::arg("g1"), nb::arg("gamma1"), nb::arg("gdd1"), nb::arg("nw"),
           "(status, tau, kind, k): AdaptiveRun._first_event in free flight (status 1: an event; 0: none; -1: Python)");
}
