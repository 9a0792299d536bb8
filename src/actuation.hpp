// The joint torques of the run loop (src/run.cpp's Runner): moreau_sim/actuation.py's Actuation.torque in C++, the
// scene's PD targets (PDGroup) and an MJCF body's <motor>/<position> actuators (mjcf_actuators.Servos) with their
// schedules (prescribed.Schedule), the effort clamps, and a Python controller called back once per step; each
// operation as numpy does it, in the same order, so that tau is the Python run's bit for bit (docs/theory.md §2.1,
// §5.5). Read from the Python objects by compiled_run._actuation. Included by run.cpp.

#include <cmath>
#include <cstring>
#include <optional>
#include <vector>

#include "rheonomic.hpp"

namespace actuation {

// numpy's float minimum, maximum and clip (NaN propagates; on ties the first operand, as numpy's scalar loops)
inline double np_minimum(double a, double b) { return (a <= b || std::isnan(a)) ? a : b; }
inline double np_maximum(double a, double b) { return (a >= b || std::isnan(a)) ? a : b; }
inline double np_clip(double x, double lo, double hi) {
  const double y = std::isnan(x) ? x : (x > lo ? x : lo);
  return std::isnan(y) ? y : (y < hi ? y : hi);
}
// Python's max(a, b) and min(a, b) (the first unless the second is strictly beyond it)
inline double py_max(double a, double b) { return b > a ? b : a; }
inline double py_min(double a, double b) { return b < a ? b : a; }

using rheonomic::Schedule;  // prescribed.Schedule (src/rheonomic.hpp)

// one group of Actuation.groups: a PDGroup ("pd") or an MJCF body's Servos ("mjcf"); torque(): its torque on each
// of its entries (v_index: the velocity row of each)
struct Group {
  bool pd = true;
  std::vector<int64_t> qi, vi;
  // PDGroup
  double kp = 0, kd = 0, effort = 0;
  Schedule target;
  std::optional<Schedule> velocity;
  // Servos
  std::vector<double> gear, gain, kps, kvs, clo, chi, flo, fhi;
  std::vector<std::optional<Schedule>> ctrl;
  std::vector<std::tuple<std::vector<int64_t>, double, double>> clamps;  // (indices, lower, upper)
  mutable std::vector<double> x_, xd_, c_;

  void torque(double t, const VectorXd &q, const VectorXd &u, std::vector<double> &tau) const {
    const size_t n = qi.size();
    tau.resize(n);
    if (pd) {  // PDGroup.torque
      x_.resize(n), xd_.resize(n), c_.resize(n);
      target.at(t, x_.data(), xd_.data());
      if (velocity) velocity->at(t, xd_.data(), c_.data());
      for (size_t j = 0; j < n; ++j)
        tau[j] = np_clip(kp * (x_[j] - q[qi[j]]) + kd * (xd_[j] - u[vi[j]]), -effort, effort);
      return;
    }
    // Servos.torque: c = clip(c(t), ctrlrange); tau = gear clip(gain c - kp (gear q) - kv (gear u), forcerange)
    for (size_t i = 0; i < n; ++i) {
      double c = 0.0;
      if (ctrl[i]) {
        x_.resize(ctrl[i]->n), xd_.resize(ctrl[i]->n);
        ctrl[i]->at(t, x_.data(), xd_.data());
        c = x_[0];
      }
      c = np_clip(c, clo[i], chi[i]);
      const double g = gear[i];
      const double f = gain[i] * c - kps[i] * (g * q[qi[i]]) - kvs[i] * (g * u[vi[i]]);
      tau[i] = g * np_clip(f, flo[i], fhi[i]);
    }
    for (const auto &[idx, lo, hi] : clamps) {  // the joint's actuatorfrcrange on the sum of its actuators
      double total = 0.0;
      for (int64_t i : idx) total += tau[(size_t)i];
      for (int64_t i : idx) tau[(size_t)i] = 0.0;
      tau[(size_t)idx[0]] = py_min(py_max(total, lo), hi);
    }
  }

  // ("pd", qi, vi, kp, kd, effort, target, velocity or None) or
  // ("mjcf", qi, vi, gear, gain, kp, kv, clo, chi, flo, fhi, [ctrl or None], [(indices, lower, upper)])
  static Group from(const nb::handle &h) {
    auto tp = nb::cast<nb::tuple>(h);
    Group g;
    g.pd = nb::cast<std::string>(tp[0]) == "pd";
    g.qi = nb::cast<std::vector<int64_t>>(tp[1]);
    g.vi = nb::cast<std::vector<int64_t>>(tp[2]);
    if (g.pd) {
      g.kp = nb::cast<double>(tp[3]), g.kd = nb::cast<double>(tp[4]), g.effort = nb::cast<double>(tp[5]);
      g.target = Schedule::from(tp[6]);
      if (!tp[7].is_none()) g.velocity = Schedule::from(tp[7]);
      return g;
    }
    std::vector<double> *arrays[] = {&g.gear, &g.gain, &g.kps, &g.kvs, &g.clo, &g.chi, &g.flo, &g.fhi};
    for (size_t k = 0; k < 8; ++k) *arrays[k] = nb::cast<std::vector<double>>(tp[3 + k]);
    for (auto c : nb::cast<nb::list>(tp[11]))
      g.ctrl.push_back(c.is_none() ? std::nullopt : std::optional<Schedule>(Schedule::from(c)));
    g.clamps = nb::cast<std::vector<std::tuple<std::vector<int64_t>, double, double>>>(tp[12]);
    return g;
  }
};

// Actuation.torque of one model: the groups' torques added on their rows (np.add.at), the controller's added, the
// effort limits clamped
class Actuation {
 public:
  // (nv, limit, groups, callback or None), compiled_run._actuation; callback: compiled_run._Callback, whose
  // `controller` f(t, q_m, u) -> tau is called here directly with arrays from callback.array (read-only to it), its
  // answer taken where it is an (nv,) float64 buffer (finite, zero on `root_rows`) and passed to callback.check
  // otherwise (numpy's conversion; actuation.Actuation's one-line errors), an exception to callback.failed;
  // callback.last: the last (t, q, u, tau) taken
  explicit Actuation(const nb::tuple &a) {
    nv_ = nb::cast<int64_t>(a[0]);
    limit_ = nb::cast<std::vector<double>>(a[1]);
    for (double l : limit_) clamped_ = clamped_ || std::isfinite(l);
    for (auto g : nb::cast<nb::list>(a[2])) groups_.push_back(Group::from(g));
    callback_ = nb::borrow(a[3]);
    if (!callback_.is_none()) {
      controller_ = callback_.attr("controller");
      root_ = nb::cast<std::vector<int64_t>>(callback_.attr("root_rows"));
      f_.resize((size_t)nv_);
    }
  }

  bool calls_python() const { return !callback_.is_none(); }

  // tau at (t [s], q, u) [N or N m]; false: the controller failed (tau undefined)
  bool torque(double t, const VectorXd &q, const VectorXd &u, VectorXd &tau) {
    tau = VectorXd::Zero(nv_);
    for (const auto &g : groups_) {
      g.torque(t, q, u, part_);
      for (size_t j = 0; j < g.vi.size(); ++j) tau[g.vi[j]] = tau[g.vi[j]] + part_[j];
    }
    if (!callback_.is_none()) {
      if (!call(t, q, u)) return false;
      for (int64_t i = 0; i < nv_; ++i) tau[i] = tau[i] + f_[(size_t)i];
    }
    if (clamped_) {
      for (int64_t i = 0; i < nv_; ++i) tau[i] = np_minimum(tau[i], limit_[i]);
      for (int64_t i = 0; i < nv_; ++i) tau[i] = np_maximum(tau[i], -limit_[i]);
    }
    return true;
  }

 private:
  int64_t nv_ = 0;
  std::vector<double> limit_;
  bool clamped_ = false;
  std::vector<Group> groups_;
  nb::object callback_, controller_;
  std::vector<int64_t> root_;  // the rows of unfixed root joints (never actuated)
  std::vector<double> part_, f_;  // f_: the controller's last answer
  // the arrays the controller is given (q_m, u_k) and their data; last_: the tuple set as callback.last
  nb::object qa_, ua_, last_;
  double *qp_ = nullptr, *up_ = nullptr;

  // the controller's answer at (t, q, u) into f_; false: it failed (the callback holds the error)
  bool call(double t, const VectorXd &q, const VectorXd &u) {
    load(qa_, qp_, q);
    load(ua_, up_, u);
    nb::object f;
    try {
      f = controller_(t, qa_, ua_);
    } catch (nb::python_error &e) {
      callback_.attr("failed")(t, e.value());
      return false;
    }
    if (!take(f)) {
      f = callback_.attr("check")(t, f);  // converted and checked as the Python run does, or None: failed
      if (f.is_none()) return false;
      if (!take(f)) throw nb::value_error("controller: the checked answer is not an (nv,) float64 array");
    }
    last_ = nb::make_tuple(t, qa_, ua_, f);
    callback_.attr("last") = last_;
    return true;
  }

  // x into the array `a` (data p) the controller is given: the same array as last step where nothing but this object
  // and last_ refers to it, a new one (callback.array) where anything else does (the controller kept it, a view of
  // it, or an error's traceback did): what the controller keeps is its own and never rewritten, as in the Python run
  void load(nb::object &a, double *&p, const VectorXd &x) {
    Py_ssize_t held = 1;
    if (a.is_valid() && last_.is_valid())
      for (Py_ssize_t i = 1; i < 4; ++i) held += PyTuple_GET_ITEM(last_.ptr(), i) == a.ptr();
    if (!a.is_valid() || Py_REFCNT(a.ptr()) != held) {
      a = callback_.attr("array")(x.size());
      Py_buffer view;
      if (PyObject_GetBuffer(a.ptr(), &view, PyBUF_C_CONTIGUOUS) != 0) throw nb::python_error();
      const bool ok = view.len == (Py_ssize_t)sizeof(double) * (Py_ssize_t)x.size();
      p = static_cast<double *>(view.buf);  // owned by a, which holds it for its life (numpy.empty)
      PyBuffer_Release(&view);
      if (!ok) throw nb::value_error("controller: callback.array gave the wrong size");
    }
    std::memcpy(p, x.data(), sizeof(double) * (size_t)x.size());
  }

  // f_ = f where f is a C-contiguous buffer of nv float64 (numpy.asarray(f, float) would be f itself), all finite,
  // zero on the root rows (Actuation._call's checks); false otherwise (f_ undefined)
  bool take(const nb::handle &f) {
    Py_buffer view;
    if (PyObject_GetBuffer(f.ptr(), &view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) != 0) {
      PyErr_Clear();
      return false;
    }
    bool ok = view.ndim == 1 && view.itemsize == (Py_ssize_t)sizeof(double) && view.format != nullptr &&
              std::strcmp(view.format, "d") == 0 && view.len == (Py_ssize_t)sizeof(double) * nv_;
    if (ok) {
      std::memcpy(f_.data(), view.buf, sizeof(double) * (size_t)nv_);
      for (double x : f_) ok = ok && std::isfinite(x);
      for (int64_t r : root_) ok = ok && f_[(size_t)r] == 0.0;
    }
    PyBuffer_Release(&view);
    return ok;
  }
};

}  // namespace actuation
