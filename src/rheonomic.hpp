// The rheonomic data of a model (docs/theory.md §2.9, §2.13): the schedules x(t) of moving statics (prescribed.py)
// and of driven joints (drive.py), evaluated here from data handed over once (moreau_sim/compiled.py
// Stepper.rheonomic; the PD targets' schedules of src/actuation.hpp likewise), operation by operation as
// prescribed.Schedule.at makes them (the sine through the same libm, the table's segment as np.searchsorted finds
// it), so that the compiled step places, rates and drives as the Python step does, bit for bit. Included by
// step.cpp (before its Stepper) and actuation.hpp.
#pragma once

#include <nanobind/nanobind.h>
#include <nanobind/stl/string.h>
#include <nanobind/stl/vector.h>
#include <pinocchio/multibody/geometry.hpp>
#include <pinocchio/spatial/se3.hpp>

#include <cmath>
#include <string>
#include <vector>

namespace rheonomic {

// prescribed.Schedule: x(t) and dx/dt(t) of n components
struct Schedule {
  enum class Kind { CONSTANT, TABLE, SINE } kind = Kind::CONSTANT;
  std::vector<std::vector<double>> x;  // rows (constant, sine: one row, the offset)
  std::vector<double> t, amplitude, rate;  // table times [s]; sine amplitudes; constant velocity (has_rate)
  double frequency = 0.0, phase = 0.0;
  bool has_rate = false;
  size_t n = 0;

  // (kind, x rows, t, amplitude, frequency, phase, rate or None), compiled.schedule
  static Schedule from(const nanobind::handle &h) {
    auto tp = nanobind::cast<nanobind::tuple>(h);
    Schedule s;
    const auto kind = nanobind::cast<std::string>(tp[0]);
    if (kind == "constant") s.kind = Kind::CONSTANT;
    else if (kind == "table") s.kind = Kind::TABLE;
    else if (kind == "sine") s.kind = Kind::SINE;
    else throw nanobind::value_error(("schedule kind: " + kind).c_str());
    s.x = nanobind::cast<std::vector<std::vector<double>>>(tp[1]);
    s.t = nanobind::cast<std::vector<double>>(tp[2]);
    s.amplitude = nanobind::cast<std::vector<double>>(tp[3]);
    s.frequency = nanobind::cast<double>(tp[4]);
    s.phase = nanobind::cast<double>(tp[5]);
    s.has_rate = !tp[6].is_none();
    if (s.has_rate) s.rate = nanobind::cast<std::vector<double>>(tp[6]);
    s.n = s.x.empty() ? 0 : s.x[0].size();
    return s;
  }

  // Schedule.at(t) into x, xd (n each)
  void at(double tq, double *xo, double *xd) const {
    const std::vector<double> &x0 = x[0];
    if (kind == Kind::SINE) {
      const double w = (2.0 * M_PI) * frequency;
      const double s = w * tq + phase;
      const double sn = std::sin(s), cs = std::cos(s);
      for (size_t j = 0; j < n; ++j) xo[j] = x0[j] + amplitude[j] * sn, xd[j] = amplitude[j] * (w * cs);
      return;
    }
    if (has_rate) {
      for (size_t j = 0; j < n; ++j) xo[j] = x0[j] + rate[j] * tq, xd[j] = rate[j];
      return;
    }
    if (kind == Kind::CONSTANT || tq < t[0]) {
      for (size_t j = 0; j < n; ++j) xo[j] = x0[j], xd[j] = 0.0;
      return;
    }
    size_t right = 0;  // np.searchsorted(t, tq, side="right"): the times <= tq
    while (right < t.size() && !(tq < t[right])) ++right;
    const size_t k = right - 1;
    if (k >= t.size() - 1) {
      for (size_t j = 0; j < n; ++j) xo[j] = x.back()[j], xd[j] = 0.0;
      return;
    }
    const double dt = t[k + 1] - t[k];
    for (size_t j = 0; j < n; ++j) {
      const double v = (x[k + 1][j] - x[k][j]) / dt;
      xo[j] = x[k][j] + v * (tq - t[k]), xd[j] = v;
    }
  }
};

// prescribed.Moving: a static that follows a schedule of its displacement (3 components), its placement at t = 0
// less x(0) (base); Prescribed.place puts it at SE3(base.rotation, base.translation + x(t))
struct Moving {
  size_t geometry = 0;
  pinocchio::SE3 base;
  Schedule schedule;
};

// The moving statics and the driven joints of one model (prescribed.Prescribed, drive.Drive)
struct Model {
  std::vector<Moving> moving;
  std::vector<int> moving_of;  // per geometry: its index in `moving`, -1 for none
  std::vector<Eigen::Index> d, r;  // Drive.d (the driven velocity rows, increasing), Drive.r (the others)
  std::vector<Schedule> drives;  // the schedule of each driven row, in the order of d

  bool driven() const { return !d.empty(); }
  // Prescribed.place: the moving statics where they are at t [s] (the geometry model's placements)
  void place(pinocchio::GeometryModel &gm, double t) const {
    double x[3], xd[3];
    for (const Moving &m : moving) {
      m.schedule.at(t, x, xd);
      const Eigen::Vector3d tr(m.base.translation()[0] + x[0], m.base.translation()[1] + x[1],
                               m.base.translation()[2] + x[2]);
      gm.geometryObjects[m.geometry].placement = pinocchio::SE3(m.base.rotation(), tr);
    }
  }
  // the velocity V(t) [m/s] of geometry g's static (-1 in moving_of: none, false)
  bool velocity(size_t g, double t, Eigen::Vector3d &V) const {
    if (g >= moving_of.size() || moving_of[g] < 0) return false;
    double x[3];
    moving[(size_t)moving_of[g]].schedule.at(t, x, V.data());
    return true;
  }
  // Drive.velocity: xdot(t) [m/s or rad/s] of the driven rows
  void drive_velocity(double t, Eigen::VectorXd &xdot) const {
    xdot.resize((Eigen::Index)drives.size());
    double x;
    for (size_t j = 0; j < drives.size(); ++j) drives[j].at(t, &x, xdot.data() + j);
  }
};

}  // namespace rheonomic
