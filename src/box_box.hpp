// The box-box pieces of the compiled detection (included by src/step.cpp): what contacts.detect does for a
// pair of two boxes (moreau_sim/contacts.py _near_polytopes, _face_axis, the edge crossings and face corners of
// moreau_sim/box_box.py edge_crossings and face_patch, docs/theory.md §6.2), as plain functions on the joint placements.
// Every sum is in index order, as box_box.py's (its _dot, _dots, _rt) and sums.ordered make them, so the edge
// crossings and face corners, which become contact rows (Stepper::detect), are Python's bit for bit; corners
// (a vertex at two faces) still hand the step back.
#pragma once

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <vector>

namespace boxbox {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using RowsX3 = Eigen::Matrix<double, Eigen::Dynamic, 3, Eigen::RowMajor>;

// a row of F (k, 3) times R.T: sum_j F_fj R_ij in index order (numpy's F @ R.T for one row)
inline Vec3 row_rt(const RowsX3 &F, Eigen::Index f, const Mat3 &R) {
  Vec3 out;
  for (int i = 0; i < 3; ++i) out[i] = (F(f, 0) * R(i, 0) + F(f, 1) * R(i, 1)) + F(f, 2) * R(i, 2);
  return out;
}
inline double dot3(const Vec3 &a, const Vec3 &b) { return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]; }
// R.T x summed in index order (sums.dots(R.T, x): a point in a box's frame, its planes' distances exact both ways)
inline Vec3 rt_times(const Mat3 &R, const Vec3 &x) {
  Vec3 out;
  for (int j = 0; j < 3; ++j) out[j] = (R(0, j) * x[0] + R(1, j) * x[1]) + R(2, j) * x[2];
  return out;
}
inline Vec3 cross3(const Vec3 &a, const Vec3 &b) {
  return Vec3(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]);
}

// a 3-term product as sums.ordered sums it (contacts._face_axis: V R', F R', Va N'): in index order, then + 0.0
inline double ordered3(const double *a, const double *b, Eigen::Index sa, Eigen::Index sb) {
  return ((a[0] * b[0] + a[sa] * b[sb]) + a[2 * sa] * b[2 * sb]) + 0.0;
}
// a row of F times R.T as sums.ordered sums it
inline Vec3 row_rt_ordered(const RowsX3 &F, Eigen::Index f, const Mat3 &R) {
  Vec3 out;
  for (int i = 0; i < 3; ++i) out[i] = ordered3(&F(f, 0), &R(i, 0), 1, 3);  // R column-major: R(i, k) at i + 3 k
  return out;
}

// contacts._face_axis: among the outward face normals of A (negated) and B (oriented B -> A), the one of largest
// s(n) = min_A n.x - max_B n.x (the first such); VA, VB: the boxes' vertices in their joint frames, FA, FB: face
// normals in the joint frames, (RA, tA), (RB, tB): the joint placements
// (ties: two equal boxes face on face; the products are sums.ordered's, ordered3, so that a tie breaks alike)
inline Vec3 face_axis(const RowsX3 &VA, const Mat3 &RA, const Vec3 &tA, const RowsX3 &FA, const RowsX3 &VB,
                      const Mat3 &RB, const Vec3 &tB, const RowsX3 &FB) {
  std::vector<Vec3> N;
  for (Eigen::Index f = 0; f < FA.rows(); ++f) N.push_back(-row_rt_ordered(FA, f, RA));
  for (Eigen::Index f = 0; f < FB.rows(); ++f) N.push_back(row_rt_ordered(FB, f, RB));
  std::vector<Vec3> wa, wb;
  for (Eigen::Index i = 0; i < VA.rows(); ++i) wa.push_back(row_rt_ordered(VA, i, RA) + tA);
  for (Eigen::Index i = 0; i < VB.rows(); ++i) wb.push_back(row_rt_ordered(VB, i, RB) + tB);
  size_t best = 0;
  double best_sep = -INFINITY;
  for (size_t f = 0; f < N.size(); ++f) {
    double lo = INFINITY, hi = -INFINITY;
    for (const Vec3 &x : wa) lo = std::min(lo, ordered3(x.data(), N[f].data(), 1, 1));
    for (const Vec3 &x : wb) hi = std::max(hi, ordered3(x.data(), N[f].data(), 1, 1));
    const double sep = lo - hi;
    if (f == 0 || sep > best_sep) best_sep = sep, best = f;
  }
  return N[best];
}

// One box's 12 edges (box_box.box_edges) in its joint frame: starts, unit directions, lengths, the normals of
// the two faces that meet there
struct Edges {
  RowsX3 e0, ed;
  Eigen::VectorXd el;
  RowsX3 f0, f1;
};

// edge_candidates (below): box_box.edge_crossings before its depth test against the boxes' overlap (applied by the
// caller), then face_patch's corners: the rows (g, p_A, p_B, n) of the edge pairs (k, l), in the order of 12 k + l, whose normal lies in both edges' normal cones (to cone), whose lines are within tol (g <= tol)
// and whose closest points are inside both edges (edge_end of the length from either end); parallel edges
// (|e_A x e_B| <= parallel) never count.
// box_box.overlap: the boxes' penetration depth (the least overlap of their projections over the 15 separating
// axes; negative where one separates them); (R, c, half) of each box in the world
inline double overlap(const Mat3 &Ra, const Vec3 &ca, const Vec3 &ha, const Mat3 &Rb, const Vec3 &cb, const Vec3 &hb,
                      double parallel) {
  std::vector<Vec3> axes;
  for (int i = 0; i < 3; ++i) axes.push_back(Ra.col(i));
  for (int i = 0; i < 3; ++i) axes.push_back(Rb.col(i));
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      const Vec3 c = cross3(Ra.col(i), Rb.col(j));
      const double s = std::sqrt(dot3(c, c));
      if (s > parallel) axes.push_back(c / s);
    }
  const Vec3 d = ca - cb;
  double out = INFINITY;
  for (const Vec3 &a : axes) {
    double pa = 0.0, pb = 0.0;
    for (int j = 0; j < 3; ++j) pa = pa + std::abs(dot3(a, Ra.col(j))) * ha[j], pb = pb + std::abs(dot3(a, Rb.col(j))) * hb[j];
    out = std::min(out, (pa + pb) - std::abs(dot3(a, d)));
  }
  return out;
}

// box_box.depth_floor: the deepest gap a contact of two crossed boxes may have, -(depth_ratio max(overlap, 0) + tol)
// (an edge crossing or face corner below it is no contact; coal's pair contact below it is its EPA failing)
inline double depth_floor(const Mat3 &Ra, const Vec3 &ca, const Vec3 &ha, const Mat3 &Rb, const Vec3 &cb,
                          const Vec3 &hb, double parallel, double depth_ratio, double tol) {
  return -(depth_ratio * std::max(overlap(Ra, ca, ha, Rb, cb, hb, parallel), 0.0) + tol);
}

// an edge crossing (face: false, feature 12 k + l) or a face corner (face: true, feature its index in the clipped
// polygon): box_box.edge_crossings' and face_patch's (g, p_A, p_B, n, ...) rows
struct Crossing {
  double g;
  Vec3 pa, pb, n;
  bool face;
  int feature;
};

// box_box.FACE_ANGLE [rad] (compiled.CONSTANTS has no slot for it: src/step.cpp reads a fixed set of names;
// tests/test_face_patch.py checks the two values are equal)
constexpr double FACE_ANGLE = 0.7853981633974483;  // pi / 4

// box_box.face_patch on the 12 world edges of each box (starts a0, directions ea, lengths el): the clipped
// corners with g <= tol appended to out. Their depth test against the boxes' overlap is the caller's (src/step.cpp
// applies it to every candidate, as Python applies it to crossings and corners apart: the same floor, and a floor
// below zero removes no g >= 0); Stepper::detect keeps them only where coal's patch has no polygon (contacts.detect).
inline void face_patch(const Vec3 *a0, const Vec3 *ea, const Eigen::VectorXd &la, const Vec3 *b0, const Vec3 *eb,
                       const Eigen::VectorXd &lb, double tol, std::vector<Crossing> &out) {
  const Vec3 Ua[3] = {ea[0], ea[4], ea[8]}, Ub[3] = {eb[0], eb[4], eb[8]};
  const double ha[3] = {0.5 * la[0], 0.5 * la[4], 0.5 * la[8]}, hb[3] = {0.5 * lb[0], 0.5 * lb[4], 0.5 * lb[8]};
  const Vec3 ca = ((a0[0] + ha[0] * Ua[0]) + ha[1] * Ua[1]) + ha[2] * Ua[2];
  const Vec3 cb = ((b0[0] + hb[0] * Ub[0]) + hb[1] * Ub[1]) + hb[2] * Ub[2];
  const Vec3 d = ca - cb;
  int best = 0;
  double s_best = -INFINITY;
  Vec3 n_best = Vec3::Zero();
  for (int f = 0; f < 12; ++f) {
    const Vec3 n = f < 6 ? (f < 3 ? Ua[f % 3] : Vec3(-Ua[f % 3])) : (f < 9 ? Vec3(-Ub[f % 3]) : Ub[f % 3]);
    const double pa = (std::abs(dot3(n, Ua[0])) * ha[0] + std::abs(dot3(n, Ua[1])) * ha[1]) + std::abs(dot3(n, Ua[2])) * ha[2];
    const double pb = (std::abs(dot3(n, Ub[0])) * hb[0] + std::abs(dot3(n, Ub[1])) * hb[1]) + std::abs(dot3(n, Ub[2])) * hb[2];
    const double sep = (dot3(n, d) - pa) - pb;
    if (f == 0 || sep > s_best) best = f, s_best = sep, n_best = n;
  }
  const bool ref_a = best < 6;
  const int i = best % 3;
  const Vec3 *Ur = ref_a ? Ua : Ub, *Ui = ref_a ? Ub : Ua;
  const double *hr = ref_a ? ha : hb, *hi = ref_a ? hb : ha;
  const Vec3 cr = ref_a ? ca : cb, ci = ref_a ? cb : ca;
  const Vec3 n = n_best, o = ref_a ? Vec3(-n_best) : n_best;
  const double c[3] = {dot3(o, Ui[0]), dot3(o, Ui[1]), dot3(o, Ui[2])};
  int j = 0;
  for (int k = 1; k < 3; ++k)
    if (std::abs(c[k]) > std::abs(c[j])) j = k;
  if (!(std::abs(c[j]) >= std::cos(FACE_ANGLE))) return;
  const int j1 = (j + 1) % 3, j2 = (j + 2) % 3;
  const Vec3 fc = ci - (c[j] > 0.0 ? hi[j] : -hi[j]) * Ui[j];
  std::vector<Vec3> poly;
  const double sg[4][2] = {{-1.0, -1.0}, {1.0, -1.0}, {1.0, 1.0}, {-1.0, 1.0}};
  for (const auto &sv : sg) poly.push_back((fc + (sv[0] * hi[j1]) * Ui[j1]) + (sv[1] * hi[j2]) * Ui[j2]);
  for (int k : {(i + 1) % 3, (i + 2) % 3})
    for (double sign : {1.0, -1.0}) {
      const Vec3 axis = sign * Ur[k];
      const double lim = hr[k] + dot3(axis, cr);
      std::vector<Vec3> clipped;
      for (size_t m = 0; m < poly.size(); ++m) {
        const Vec3 &p = poly[m], &q = poly[(m + 1) % poly.size()];
        const double dp = dot3(axis, p) - lim, dq = dot3(axis, q) - lim;
        if (dp <= 0.0) clipped.push_back(p);
        if ((dp < 0.0 && 0.0 < dq) || (dq < 0.0 && 0.0 < dp)) clipped.push_back(p + (dp / (dp - dq)) * (q - p));
      }
      poly = clipped;
      if (poly.empty()) return;
    }
  const double plane = dot3(o, cr + hr[i] * o);
  for (size_t m = 0; m < poly.size(); ++m) {
    const Vec3 &p = poly[m];
    const double g = dot3(o, p) - plane;
    if (g <= tol) out.push_back({g, ref_a ? Vec3(p + g * n) : p, ref_a ? p : Vec3(p - g * n), n, true, (int)m});
  }
}

inline std::vector<Crossing> edge_candidates(const Edges &A, const Mat3 &RA, const Vec3 &tA, const Edges &B,
                                         const Mat3 &RB, const Vec3 &tB, double tol, double cone, double edge_end,
                                         double parallel) {
  std::vector<Crossing> out;
  Vec3 a0[12], ea[12], fa[12][2], b0[12], eb[12], fb[12][2];
  for (int k = 0; k < 12; ++k) {
    a0[k] = row_rt(A.e0, k, RA) + tA, ea[k] = row_rt(A.ed, k, RA);
    fa[k][0] = row_rt(A.f0, k, RA), fa[k][1] = row_rt(A.f1, k, RA);
    b0[k] = row_rt(B.e0, k, RB) + tB, eb[k] = row_rt(B.ed, k, RB);
    fb[k][0] = row_rt(B.f0, k, RB), fb[k][1] = row_rt(B.f1, k, RB);
  }
  for (int k = 0; k < 12; ++k)
    for (int l = 0; l < 12; ++l) {
      const Vec3 c = cross3(ea[k], eb[l]);
      const double s = std::sqrt(dot3(c, c));
      if (!(s > parallel)) continue;
      Vec3 n = c / s;
      double nb0 = dot3(n, fb[l][0]), nb1 = dot3(n, fb[l][1]);
      if (nb0 + nb1 < 0.0) n = -n, nb0 = -nb0, nb1 = -nb1;
      const double na0 = dot3(n, fa[k][0]), na1 = dot3(n, fa[k][1]);
      if (!(std::min(nb0, nb1) >= -cone && std::max(na0, na1) <= cone)) continue;
      // outside a cone by less than `cone`: the cone's nearest direction, the face normal at its other end, A's
      // cone first (box_box.edge_crossings, docs/theory.md §6.2)
      if (std::max(na0, na1) > 0.0) n = -(na0 >= na1 ? fa[k][1] : fa[k][0]);
      else if (std::min(nb0, nb1) < 0.0) n = (nb0 <= nb1 ? fb[l][1] : fb[l][0]);
      const Vec3 w = a0[k] - b0[l];
      const double g = dot3(n, w);
      if (!(g <= tol)) continue;
      const double bb = dot3(ea[k], eb[l]), d = dot3(ea[k], w), e = dot3(eb[l], w), den = s * s;
      const double sa = (bb * e - d) / den, tb = (e - bb * d) / den;
      const double la = A.el[k], lb = B.el[l];
      if (!(sa >= edge_end * la && sa <= (1.0 - edge_end) * la)) continue;
      if (!(tb >= edge_end * lb && tb <= (1.0 - edge_end) * lb)) continue;
      out.push_back({g, a0[k] + sa * ea[k], b0[l] + tb * eb[l], n, false, 12 * k + l});
    }
  face_patch(a0, ea, A.el, b0, eb, B.el, tol, out);
  return out;
}

}  // namespace boxbox
