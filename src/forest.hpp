// The forest's figures as trees.Forest and contacts.pair_distances compute them: kinetic and potential energy and
// the pairs' distances at a state, on the forest's own Pinocchio Datas and the Stepper's GeometryData (the Python
// run's, data.geom). One home for what a sample records (recording.Recorder.sample): run.cpp's Runner and
// adaptive.hpp's DenseSampler. #included by run.cpp (its helpers: extract_ref, Stepper).

class ForestFigures {
 public:
  using TreeArgs = std::vector<std::tuple<nb::object, nb::object, int64_t, int64_t, int64_t, int64_t>>;
  // trees: (pin.Model, pin.Data, q start, nq, v start, nv) per tree of the forest (trees.Forest, its Kinematics'
  // datas); tree_of_joint, local_joint: the forest's maps
  ForestFigures(Stepper &S, const TreeArgs &trees, std::vector<int64_t> tree_of_joint, std::vector<int64_t> local_joint)
      : S_(S), tree_of_joint_(std::move(tree_of_joint)), local_joint_(std::move(local_joint)) {
    for (auto &t : trees) {
      py_trees_.push_back(std::get<0>(t)), py_trees_.push_back(std::get<1>(t));
      Tree tr{&extract_ref<pinocchio::Model>(std::get<0>(t), "pinocchio.Model"),
              &extract_ref<pinocchio::Data>(std::get<1>(t), "pinocchio.Data"), std::get<2>(t), std::get<3>(t),
              std::get<4>(t), std::get<5>(t)};
      trees_.push_back(tr);
    }
  }

  // (each tree's q and u as views of the forest's, not copies: Pinocchio's functions take them as Eigen::Ref)
  using CRef = Eigen::Ref<const VectorXd>;
  double kinetic(const VectorXd &q, const VectorXd &u) {  // Forest.kinetic
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
  double potential(const VectorXd &q) {  // Forest.potential
    double s = 0.0;
    for (auto &tr : trees_) s += pinocchio::computePotentialEnergy(*tr.model, *tr.data, CRef(q.segment(tr.q0, tr.nq)));
    return s;
  }
  size_t pairs() const { return S_.gm_.collisionPairs.size(); }
  // contacts.pair_distances into `out` (Forest.place with the geometry placements, then coal's distances)
  void gaps(const VectorXd &q, double *out) {
    auto &gd = S_.gd_;
    const auto &gm = S_.gm_;
    if (gm.collisionPairs.empty()) return;
    S_.fresh_guesses(gd.distanceRequests);
    for (auto &tr : trees_) pinocchio::forwardKinematics(*tr.model, *tr.data, VectorXd(q.segment(tr.q0, tr.nq)));
    for (size_t g = 0; g < gm.geometryObjects.size(); ++g) {
      const auto &go = gm.geometryObjects[g];
      const auto j = go.parentJoint;
      if (j) {
        const Tree &tr = trees_[(size_t)tree_of_joint_[j]];
        gd.oMg[g] = tr.data->oMi[(size_t)local_joint_[j]] * go.placement;
      } else {
        gd.oMg[g] = go.placement;
      }
    }
    pinocchio::computeDistances(gm, gd);
    for (size_t k = 0; k < gd.distanceResults.size(); ++k) {
      const double x = gd.distanceResults[k].min_distance;
      out[k] = std::abs(x) < S_.C_.distance_failed ? x : std::numeric_limits<double>::quiet_NaN();
    }
  }

 private:
  struct Tree {
    const pinocchio::Model *model;
    pinocchio::Data *data;
    int64_t q0, nq, v0, nv;
  };
  Stepper &S_;
  std::vector<nb::object> py_trees_;  // keep the Python models and datas (and so the C++ ones) alive
  std::vector<Tree> trees_;
  std::vector<int64_t> tree_of_joint_, local_joint_;
};
