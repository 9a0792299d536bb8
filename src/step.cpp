#include <nanobind/nanobind.h>
#include <boost/python.hpp>
#include <pinocchio/multibody/model.hpp>
#include <pinocchio/multibody/data.hpp>
#include <pinocchio/algorithm/crba.hpp>
namespace nb = nanobind;
namespace bp = boost::python;
static double nv_of(nb::handle m) {
  bp::object o{bp::handle<>(bp::borrowed(m.ptr()))};
  pinocchio::Model &model = bp::extract<pinocchio::Model &>(o);
  return model.nv;
}
NB_MODULE(_step, m) { m.def("nv_of", &nv_of); }
