// moreau_sim/pair_table.py's PairTable in C++: the collision pairs of a scene without their list (more than
// model.LAZY_PAIRS), every two geometries i < j less the sorted keys i G + j of `removed`, pair k made from its index
// and the index of (i, j) from the pair, the same integer arithmetic as the Python class (docs/theory.md §6.1).
// The compiled Stepper queries coal only on the broad phase's candidates, through the coal objects Python's Data
// makes per pair at first use (data.Data.pair_query, distance_query): no GeometryModel nor GeometryData of every pair.
#pragma once

#include <algorithm>
#include <cstdint>
#include <utility>
#include <vector>

namespace pairs {

struct Row {  // one pair as PairTable's Pair has it: the geometry on the larger joint first
  int first, second, joint_first, joint_second;
  bool patch;
};

struct Table {
  int64_t G = 0;
  std::vector<int64_t> joint, removed, start;  // per geometry; sorted keys i G + j; first pair of row i (G + 1)
  std::vector<char> half, poly, flat, faces;  // per geometry: half-space or plane, polytope, flat faces, and
                                              // faces with vertices (model.polytope_pair_set: two of them)

  int64_t size() const { return start.empty() ? 0 : start.back(); }
  // PairTable.chosen: whether geometries i, j (any order) form a pair
  bool chosen(int64_t i, int64_t j) const {
    const int64_t lo = std::min(i, j), hi = std::max(i, j);
    return lo != hi && !std::binary_search(removed.begin(), removed.end(), lo * G + hi);
  }
  // PairTable.index: the pair of geometries i, j (any order; a pair: chosen)
  int64_t index(int64_t i, int64_t j) const {
    const int64_t lo = std::min(i, j), hi = std::max(i, j);
    const int64_t before = (std::lower_bound(removed.begin(), removed.end(), lo * G + hi) - removed.begin()) -
                           (std::lower_bound(removed.begin(), removed.end(), lo * G + lo) - removed.begin());
    return start[(size_t)lo] + (hi - lo - 1) - before;
  }
  // PairTable.geometries: (i, j), i < j, of pair k
  std::pair<int64_t, int64_t> geometries(int64_t k) const {
    const int64_t i = (std::upper_bound(start.begin(), start.end(), k) - start.begin()) - 1;
    int64_t j = i + 1 + (k - start[(size_t)i]);
    auto a = std::lower_bound(removed.begin(), removed.end(), i * G + i);
    const auto b = std::lower_bound(removed.begin(), removed.end(), (i + 1) * G);
    for (; a != b; ++a) {  // the row's left-out partners, in order: skip each at or before j
      if (*a - i * G <= j)
        ++j;
      else
        break;
    }
    return {i, j};
  }
  // PairTable._make: shape 1 the one on the larger joint; the patch flag
  Row row(int64_t k) const {
    auto [i, j] = geometries(k);
    if (joint[(size_t)i] < joint[(size_t)j]) std::swap(i, j);
    const size_t a = (size_t)i, b = (size_t)j;
    const bool patch = flat[a] && flat[b] && !((half[a] && poly[b]) || (half[b] && poly[a]));
    return {(int)i, (int)j, (int)joint[a], (int)joint[b], patch};
  }
  bool polytope(const Row &r) const { return faces[(size_t)r.first] && faces[(size_t)r.second]; }
};

}  // namespace pairs
