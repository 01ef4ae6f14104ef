// The non-rigid correction: an embedded deformation graph (Sumner et al. 2007) fitted to the
// live surface's point-to-plane pairs by Gauss-Newton, with the as-rigid-as-possible term
// between neighbouring nodes that keeps the scan from tearing where the data pulls hard.
#include <Eigen/Sparse>
#include <Eigen/SparseCholesky>
#include <algorithm>
#include <cmath>

#include "core/projector.h"
#include "live/internal/live.h"
#include "live/live.h"
#include "reconstruction/reconstruction.h"

namespace holocap {

namespace {

// The Gauss-Newton system's 6x6 blocks by node pair, each summed in the order its terms are
// added: the matrix is entry for entry the one that a triplet per term gave, built without a
// triplet per term (a pair's four nodes make 16 blocks of 36 entries).
class BlockSum {
 public:
  using Block = Eigen::Matrix<double, 6, 6>;
  explicit BlockSum(size_t nodes) : rows_(nodes) {}
  Block& At(int j, int k) {
    std::vector<std::pair<int, Block>>& row = rows_[static_cast<size_t>(j)];
    for (auto& [column, block] : row)
      if (column == k) return block;
    row.emplace_back(k, Block::Zero());
    return row.back().second;
  }
  Eigen::SparseMatrix<double> Matrix() const {
    std::vector<Eigen::Triplet<double>> triplets;
    for (size_t j = 0; j < rows_.size(); ++j) {
      for (const auto& [k, block] : rows_[j]) {
        for (int row = 0; row < 6; ++row)
          for (int col = 0; col < 6; ++col)
            triplets.emplace_back(static_cast<int>(6 * j) + row, 6 * k + col, block(row, col));
      }
    }
    const int unknowns = static_cast<int>(6 * rows_.size());
    Eigen::SparseMatrix<double> matrix(unknowns, unknowns);
    matrix.setFromTriplets(triplets.begin(), triplets.end());
    return matrix;
  }

 private:
  std::vector<std::vector<std::pair<int, Block>>> rows_;
};

class NonRigidSolver {
 public:
  NonRigidSolver(const Mesh& aligned, const LiveSurface& live, const LiveOptions& options,
                 DeformationGraph* graph)
      : mesh_(aligned),
        live_(live),
        options_(options),
        graph_(*graph),
        samples_(live::ThinnedVertices(aligned.vertices.size(), options.alignment_samples)),
        posed_(aligned) {}

  NonRigidFit Run() {
    NonRigidFit fit;
    fit.nodes = static_cast<int64_t>(graph_.nodes.size());
    PoseSamples(/*find_hidden=*/true);
    fit.before = Measure();
    const std::vector<Eigen::Matrix3d> start_rotation = graph_.rotation;
    const std::vector<Eigen::Vector3d> start_translation = graph_.translation;
    for (int iteration = 0; iteration < options_.nonrigid_iterations; ++iteration) {
      // The gate shrinks from four times the final one: a limb bent away from the scan's pose
      // is first caught, then fitted closely.
      const double gate = std::max(options_.gate_m, 4 * options_.gate_m * std::pow(0.5, iteration));
      live::Associate(points_, normals_, live_, gate, options_.max_normal_angle_deg, &pairs_);
      live::AddNearestPairs(points_, normals_, live_, gate, options_.max_normal_angle_deg,
                            options_.alignment_samples, &pairs_);
      if (pairs_.size() < 6 || !Step()) break;
      PoseSamples(/*find_hidden=*/gate > options_.gate_m);
    }
    fit.after = Measure();
    // A correction that fits worse than the rigid alignment is not kept.
    if (fit.after.inlier_fraction + 1e-9 < fit.before.inlier_fraction) {
      graph_.rotation = start_rotation;
      graph_.translation = start_translation;
      fit.after = fit.before;
    }
    fit.deformed = Deformed(&fit.deformation_rms_m, &fit.deformation_max_m);
    return fit;
  }

 private:
  // The samples where the graph puts them. A sample that the posed scan itself hides from the
  // sensor (a leg behind the other leg) is left out (NaN): the live surface in front of it is
  // the other limb's, and pairing it there would pull the hidden limb onto the seen one. Which
  // samples are hidden is found anew (`find_hidden`: the scan's own depth rendered) while the
  // gate is coarse, where such pairs form, and kept once it is fine.
  void PoseSamples(bool find_hidden) {
    points_.resize(samples_.size());
    normals_.resize(samples_.size());
    for (size_t s = 0; s < samples_.size(); ++s) {
      const size_t v = static_cast<size_t>(samples_[s]);
      points_[s] = graph_.Apply(v, mesh_.vertices[v].cast<double>()).cast<float>();
      normals_[s] = graph_.ApplyNormal(v, mesh_.normals[v].cast<double>()).cast<float>();
    }
    if (find_hidden) FindHidden();
    for (size_t s = 0; s < samples_.size(); ++s)
      if (hidden_[s])
        points_[s] = Eigen::Vector3f::Constant(std::numeric_limits<float>::quiet_NaN());
  }

  void FindHidden() {
    for (size_t v = 0; v < mesh_.vertices.size(); ++v)
      posed_.vertices[v] = graph_.Apply(v, mesh_.vertices[v].cast<double>()).cast<float>();
    const cv::Mat own_depth = RenderDepth(posed_, live_.camera);
    const FastProjector projector(live_.camera);
    const float margin = static_cast<float>(options_.gate_m);
    hidden_.assign(samples_.size(), 0);
    for (size_t s = 0; s < samples_.size(); ++s) {
      float u, w, z;
      if (!projector.ProjectWorld(points_[s], &u, &w, &z)) continue;
      const int x = static_cast<int>(std::lround(u)), y = static_cast<int>(std::lround(w));
      if (x < 0 || y < 0 || x >= own_depth.cols || y >= own_depth.rows) continue;
      const float front = own_depth.at<float>(y, x);
      hidden_[s] = std::isfinite(front) && z > front + margin;
    }
  }

  FitStats Measure() const {
    return MeasureFit(points_, normals_, live_, options_.gate_m, options_.max_normal_angle_deg);
  }

  // One Gauss-Newton step over every node's rotation (as a small rotation applied after its
  // current one) and translation. False when the system cannot be solved.
  bool Step() {
    const int unknowns = 6 * static_cast<int>(graph_.nodes.size());
    BlockSum blocks(graph_.nodes.size());
    Eigen::VectorXd gradient = Eigen::VectorXd::Zero(unknowns);
    AddData(&blocks, &gradient);
    AddRegulariser(&blocks, &gradient);
    // Nodes that neither data nor neighbours hold stay where they are.
    for (size_t j = 0; j < graph_.nodes.size(); ++j) {
      BlockSum::Block& diagonal = blocks.At(static_cast<int>(j), static_cast<int>(j));
      for (int d = 0; d < 6; ++d) diagonal(d, d) += 1e-6;
    }
    Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> solver(blocks.Matrix());
    if (solver.info() != Eigen::Success) return false;
    const Eigen::VectorXd step = solver.solve(-gradient);
    if (solver.info() != Eigen::Success || !step.allFinite()) return false;
    for (size_t j = 0; j < graph_.nodes.size(); ++j) {
      graph_.rotation[j] = live::SmallRotation(step.segment<3>(6 * j)) * graph_.rotation[j];
      graph_.translation[j] += step.segment<3>(6 * j + 3);
    }
    return true;
  }

  void AddData(BlockSum* hessian, Eigen::VectorXd* gradient) const {
    for (const live::Pair& pair : pairs_) {
      const size_t v = static_cast<size_t>(samples_[pair.index]);
      const double r = pair.normal.dot(points_[pair.index].cast<double>() - pair.point);
      const double weight = live::HuberWeight(r, options_.huber_m);
      int columns[4];
      Eigen::Matrix<double, 6, 1> blocks[4];
      int used = 0;
      for (int n = 0; n < 4; ++n) {
        const int j = graph_.vertex_node[v][n];
        if (j < 0) continue;
        const double alpha = graph_.vertex_weight[v][n];
        const Eigen::Vector3d arm =
            graph_.rotation[j] * (mesh_.vertices[v].cast<double>() - graph_.nodes[j]);
        blocks[used] << alpha * arm.cross(pair.normal), alpha * pair.normal;
        columns[used++] = 6 * j;
      }
      for (int a = 0; a < used; ++a) {
        gradient->segment<6>(columns[a]) += weight * r * blocks[a];
        for (int b = 0; b < used; ++b)
          hessian->At(columns[a] / 6, columns[b] / 6) += weight * blocks[a] * blocks[b].transpose();
      }
    }
  }

  // As rigid as possible: node j's motion carries its neighbour k's rest position to where
  // node k's own motion takes it.
  void AddRegulariser(BlockSum* hessian, Eigen::VectorXd* gradient) const {
    int64_t edges = 0;
    for (const std::vector<int>& neighbours : graph_.edges)
      edges += static_cast<int64_t>(neighbours.size());
    if (edges == 0) return;
    // Balanced against the data however many pairs and edges there are.
    const double weight = options_.arap_weight *
                          std::max<double>(1, static_cast<double>(pairs_.size())) /
                          static_cast<double>(edges);
    for (size_t j = 0; j < graph_.nodes.size(); ++j) {
      for (int k : graph_.edges[j]) {
        const Eigen::Vector3d arm = graph_.rotation[j] * (graph_.nodes[k] - graph_.nodes[j]);
        const Eigen::Vector3d e =
            arm + graph_.nodes[j] + graph_.translation[j] - graph_.nodes[k] - graph_.translation[k];
        // e's Jacobian: -[arm]x for node j's rotation, I for its translation, -I for k's.
        Eigen::Matrix<double, 3, 12> jacobian;
        jacobian << -Skew(arm), Eigen::Matrix3d::Identity(), Eigen::Matrix3d::Zero(),
            -Eigen::Matrix3d::Identity();
        const int columns[2] = {static_cast<int>(6 * j), 6 * k};
        const Eigen::Matrix<double, 12, 12> block = weight * jacobian.transpose() * jacobian;
        const Eigen::Matrix<double, 12, 1> g = weight * jacobian.transpose() * e;
        for (int a = 0; a < 2; ++a) {
          gradient->segment<6>(columns[a]) += g.segment<6>(6 * a);
          for (int b = 0; b < 2; ++b)
            hessian->At(columns[a] / 6, columns[b] / 6) += block.block<6, 6>(6 * a, 6 * b);
        }
      }
    }
  }

  static Eigen::Matrix3d Skew(const Eigen::Vector3d& v) {
    Eigen::Matrix3d m;
    m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
    return m;
  }

  Mesh Deformed(double* rms_m, double* max_m) const {
    Mesh deformed = mesh_;
    double squared = 0;
    *max_m = 0;
    for (size_t v = 0; v < mesh_.vertices.size(); ++v) {
      const Eigen::Vector3d rest = mesh_.vertices[v].cast<double>();
      const Eigen::Vector3d moved = graph_.Apply(v, rest);
      deformed.vertices[v] = moved.cast<float>();
      deformed.normals[v] = graph_.ApplyNormal(v, mesh_.normals[v].cast<double>()).cast<float>();
      const double d = (moved - rest).norm();
      squared += d * d;
      *max_m = std::max(*max_m, d);
    }
    *rms_m = mesh_.vertices.empty() ? 0 : std::sqrt(squared / mesh_.vertices.size());
    return deformed;
  }

  const Mesh& mesh_;
  const LiveSurface& live_;
  const LiveOptions& options_;
  DeformationGraph& graph_;
  std::vector<int> samples_;
  std::vector<Eigen::Vector3f> points_, normals_;
  std::vector<live::Pair> pairs_;
  Mesh posed_;                // the mesh where the graph puts it (its own depth hides samples)
  std::vector<char> hidden_;  // per sample
};

}  // namespace

NonRigidFit FitNonRigid(const Mesh& aligned, const LiveSurface& live, const LiveOptions& options,
                        DeformationGraph* graph) {
  if (graph != nullptr) return NonRigidSolver(aligned, live, options, graph).Run();
  DeformationGraph own(aligned, options.node_spacing_m, options.node_neighbours);
  return NonRigidSolver(aligned, live, options, &own).Run();
}

}  // namespace holocap
