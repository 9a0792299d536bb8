// Results that cross to Python as NumPy arrays owning the Eigen storage the C++ computed them in (the adaptive
// integrator's per-step calls: src/events.hpp, adaptive.hpp, impact.hpp). nanobind returns an Eigen object under
// 1 KB as a copy made by numpy.copy, a Python function (~1.3 us a call, against ~0.2 us for an array over storage
// handed to it); a run of the adaptive integrator makes hundreds of such calls. The arrays are the same: values,
// dtype float64, shape, memory order (a row-major matrix C, a column-major one F), writable. #included by step.cpp
// before the classes whose methods bind through owned::Method.

#include <tuple>
#include <type_traits>
#include <utility>

namespace owned {

// whether P is a dense Eigen matrix or vector of doubles that owns its storage
template <class P, class = void> struct plain : std::false_type {};
template <class P>
struct plain<P, std::void_t<typename P::Scalar, decltype(P::IsRowMajor)>>
    : std::bool_constant<std::is_same_v<typename P::Scalar, double> &&
                         std::is_base_of_v<Eigen::PlainObjectBase<P>, P>> {};

// x as a NumPy array over its own storage, moved to the heap and freed with the array; anything else (a StepOut,
// a bool, an empty array) as nanobind casts it
template <class T> nb::object array(T &&x) {
  using P = std::decay_t<T>;
  if constexpr (plain<P>::value) {
    if (x.size() == 0) return nb::cast(std::forward<T>(x));  // (no storage to hand over)
    P *p = new P(std::forward<T>(x));
    nb::capsule owner(p, [](void *v) noexcept { delete static_cast<P *>(v); });
    if constexpr (P::ColsAtCompileTime == 1) {
      size_t shape[1] = {(size_t)p->size()};
      return nb::cast(nb::ndarray<nb::numpy, double>(p->data(), 1, shape, owner), nb::rv_policy::reference);
    } else {
      size_t shape[2] = {(size_t)p->rows(), (size_t)p->cols()};
      int64_t strides[2] = {P::IsRowMajor ? (int64_t)p->cols() : 1, P::IsRowMajor ? 1 : (int64_t)p->rows()};
      return nb::cast(nb::ndarray<nb::numpy, double>(p->data(), 2, shape, owner, strides),
                      nb::rv_policy::reference);
    }
  } else {
    return nb::cast(std::forward<T>(x));
  }
}

// the method F of C, bound to return its tuple with each Eigen array as array() makes it
template <auto F> struct Method;
template <class C, class... R, class... A, std::tuple<R...> (C::*F)(A...)> struct Method<F> {
  static nb::tuple call(C &self, A... a) {
    return std::apply([](auto &&...x) { return nb::make_tuple(array(std::move(x))...); },
                      (self.*F)(std::forward<A>(a)...));
  }
};

}  // namespace owned
