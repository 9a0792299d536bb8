// The forest: one Pinocchio model and small Data per kinematic tree of the scene (moreau_sim/trees.py Forest and
// Kinematics, docs/theory.md §2.12), and the dynamics and kinematics the compiled step needs assembled from the
// trees operation by operation as trees.Forest assembles them: M (and the WORLD joint Jacobians) and M^-1 block by
// block, the free acceleration by ABA per tree, T and V summed term by term in the scene model's joint order, the
// joint placements by the scene's joint ids and the geometry placements oMg = oMi * placement. No Data of the whole
// scene (Pinocchio 4.1's Data holds four nv^3 tensors). The Datas are the Python run's (data.kinematics.datas()):
// both steps compute on the same objects. #included by step.cpp before its Stepper (its helpers: extract_ref).
#include <pinocchio/algorithm/kinematics.hpp>

class Forest {
 public:
  using TreeArgs = std::vector<std::tuple<nb::object, nb::object, int64_t, int64_t, int64_t, int64_t>>;
  struct Tree {
    const pinocchio::Model *model;
    pinocchio::Data *data;
    int64_t q0, nq, v0, nv;
  };
  // trees: (pin.Model, pin.Data, q start, nq, v start, nv) per tree of the forest (compiled.forest_args);
  // tree_of_joint, local_joint: the forest's maps (trees.Forest), one entry per joint of the scene's model
  Forest(const TreeArgs &trees, std::vector<int64_t> tree_of_joint, std::vector<int64_t> local_joint)
      : tree_of_joint_(std::move(tree_of_joint)), local_joint_(std::move(local_joint)) {
    if (tree_of_joint_.size() != local_joint_.size() || tree_of_joint_.empty())
      throw nb::value_error("forest: tree_of_joint and local_joint, one entry per joint");
    int64_t nq = 0, nv = 0;
    for (auto &t : trees) {
      py_.push_back(std::get<0>(t)), py_.push_back(std::get<1>(t));
      Tree tr{&extract_ref<pinocchio::Model>(std::get<0>(t), "pinocchio.Model"),
              &extract_ref<pinocchio::Data>(std::get<1>(t), "pinocchio.Data"), std::get<2>(t), std::get<3>(t),
              std::get<4>(t), std::get<5>(t)};
      if (tr.q0 != nq || tr.v0 != nv || tr.nq != tr.model->nq || tr.nv != tr.model->nv)
        throw nb::value_error("forest: the trees' slices of q and u, in order, their models' sizes");
      nq += tr.nq, nv += tr.nv;
      trees_.push_back(tr);
    }
    nq_ = nq, nv_ = nv;
    oMi_.assign(tree_of_joint_.size(), nullptr);
    for (size_t j = 1; j < tree_of_joint_.size(); ++j) {
      const int64_t t = tree_of_joint_[j], k = local_joint_[j];
      if (t < 0 || t >= (int64_t)trees_.size() || k < 1 || k >= trees_[(size_t)t].model->njoints)
        throw nb::value_error("forest: a joint's tree and local joint out of range");
      oMi_[j] = &trees_[(size_t)t].data->oMi[(size_t)k];  // a reference into the tree's Data (Kinematics.oMi)
    }
  }

  int64_t nq() const { return nq_; }
  int64_t nv() const { return nv_; }
  size_t njoints() const { return oMi_.size(); }
  const std::vector<Tree> &trees() const { return trees_; }
  const std::vector<int64_t> &tree_of_joint() const { return tree_of_joint_; }

  // (each tree's q and u as views of the forest's, not copies: Pinocchio's functions take them as Eigen::Ref)
  using CRef = Eigen::Ref<const VectorXd>;

  // Forest.kinetic: T = 1/2 sum over joints of v_i' I_i v_i in the scene's joint order (pin.computeKineticEnergy's sum)
  double kinetic(const VectorXd &q, const VectorXd &u) {
    double s = 0.0;
    for (auto &tr : trees_) {
      const CRef qt = q.segment(tr.q0, tr.nq), ut = u.segment(tr.v0, tr.nv);
      if (tr.model->njoints == 2) {
        s += 2.0 * pinocchio::computeKineticEnergy(*tr.model, *tr.data, qt, ut);
        continue;
      }
      pinocchio::forwardKinematics(*tr.model, *tr.data, qt, ut);
      for (int j = 1; j < tr.model->njoints; ++j) s += tr.model->inertias[j].vtiv(tr.data->v[j]);
    }
    return 0.5 * s;
  }
  // Forest.potential
  double potential(const VectorXd &q) {
    double s = 0.0;
    for (auto &tr : trees_) s += pinocchio::computePotentialEnergy(*tr.model, *tr.data, CRef(q.segment(tr.q0, tr.nq)));
    return s;
  }

  // Forest.place: forward kinematics of every tree at q (oMi below); with a geometry, its placements oMg as
  // pin.updateGeometryPlacements makes them (oMg[g] = oMi[joint] * placement; on the world: the placement)
  void place(const VectorXd &q) {
    for (auto &tr : trees_) pinocchio::forwardKinematics(*tr.model, *tr.data, CRef(q.segment(tr.q0, tr.nq)));
  }
  void place(const VectorXd &q, const pinocchio::GeometryModel &gm, pinocchio::GeometryData &gd) {
    place(q);
    for (size_t g = 0; g < gm.geometryObjects.size(); ++g) {
      const auto &go = gm.geometryObjects[g];
      if (go.parentJoint)
        gd.oMg[g] = *oMi_[go.parentJoint] * go.placement;
      else
        gd.oMg[g] = go.placement;
    }
  }
  // the placement of the scene's joint j after place() (or an algorithm that places: crba, aba, the energies)
  const pinocchio::SE3 &oMi(size_t j) const { return j ? *oMi_[j] : world_; }

  // Forest.mass_matrix: M's block of each tree by CRBA (WORLD; symmetrized as the Python binding returns it) into
  // M, whose other entries are left as they are (zero: the caller's), and the trees' WORLD Jacobians into J (6, nv)
  void mass_matrix(const VectorXd &q, MatrixXd &M, MatrixXd &J) {
    for (auto &tr : trees_) {
      auto &d = *tr.data;
      pinocchio::crba(*tr.model, d, CRef(q.segment(tr.q0, tr.nq)), pinocchio::Convention::WORLD);
      d.M.triangularView<Eigen::StrictlyLower>() = d.M.transpose().triangularView<Eigen::StrictlyLower>();
      M.block(tr.v0, tr.v0, tr.nv, tr.nv) = d.M;
      J.middleCols(tr.v0, tr.nv) = d.J;
    }
  }
  // Forest.inverse_mass_matrix: each tree's block of M^-1 (computeMinverse, symmetrized) into Minv (other entries
  // left as they are)
  void inverse_mass_matrix(const VectorXd &q, MatrixXd &Minv) {
    for (auto &tr : trees_) {
      auto &d = *tr.data;
      pinocchio::computeMinverse(*tr.model, d, CRef(q.segment(tr.q0, tr.nq)));
      d.Minv.triangularView<Eigen::StrictlyLower>() = d.Minv.transpose().triangularView<Eigen::StrictlyLower>();
      Minv.block(tr.v0, tr.v0, tr.nv, tr.nv) = d.Minv;
    }
  }
  // Forest.acceleration: M^-1 (tau - h(q, u)) by ABA per tree
  VectorXd acceleration(const VectorXd &q, const VectorXd &u, const VectorXd &tau) {
    VectorXd a(nv_);
    for (auto &tr : trees_)
      a.segment(tr.v0, tr.nv) = pinocchio::aba(*tr.model, *tr.data, CRef(q.segment(tr.q0, tr.nq)),
                                               CRef(u.segment(tr.v0, tr.nv)), CRef(tau.segment(tr.v0, tr.nv)));
    return a;
  }

 private:
  std::vector<nb::object> py_;  // keep the Python models and datas (and so the C++ ones) alive
  std::vector<Tree> trees_;
  std::vector<int64_t> tree_of_joint_, local_joint_;
  std::vector<const pinocchio::SE3 *> oMi_;  // by the scene's joint id (the world, 0: world_)
  pinocchio::SE3 world_ = pinocchio::SE3::Identity();
  int64_t nq_ = 0, nv_ = 0;
};
