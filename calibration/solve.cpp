// Seeding and the staged mrcal solve, with projection uncertainty from mrcal's Jacobian.
#include <Eigen/Dense>
#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <numbers>
#include <numeric>
#include <opencv2/calib3d.hpp>
#include <optional>
#include <queue>
#include <random>
#include <set>

#include "calibration/calibration.h"
#include "calibration/internal/common.h"
#include "core/check_option.h"
#include "core/error.h"

extern "C" {
#include <mrcal/mrcal.h>
#include <mrcal/poseutils.h>
#include <suitesparse/cholmod.h>
}

namespace holocap {
namespace calibration_internal {

Pose FitRigid(const std::vector<Eigen::Vector3d>& a, const std::vector<Eigen::Vector3d>& b) {
  if (a.size() != b.size() || a.size() < 3) Fail("FitRigid needs >= 3 matched points");
  Eigen::Matrix3Xd ma(3, a.size()), mb(3, b.size());
  for (size_t k = 0; k < a.size(); ++k) {
    ma.col(k) = a[k];
    mb.col(k) = b[k];
  }
  const Eigen::Matrix4d m = Eigen::umeyama(ma, mb, false);
  Pose pose = Pose::Identity();
  pose.matrix() = m;
  return pose;
}

void CheckLensmodelName(const std::string& name) {
  mrcal_lensmodel_t model;
  if (!mrcal_lensmodel_from_name(&model, name.c_str()) ||
      !mrcal_lensmodel_type_is_valid(model.type)) {
    Fail("unknown or unconfigured lens model '", name, "'");
  }
  // Names mrcal parses but its optimiser stops on with an assertion: refused as input.
  if (model.type == MRCAL_LENSMODEL_CAHVORE) {
    Fail("lens model '", name,
         "': mrcal does not optimise CAHVORE; use LENSMODEL_CAHVOR, an OPENCV model or a "
         "splined one");
  }
  if (model.type == MRCAL_LENSMODEL_SPLINED_STEREOGRAPHIC) {
    const auto& config = model.LENSMODEL_SPLINED_STEREOGRAPHIC__config;
    if ((config.order != 2 && config.order != 3) || config.Nx < 4 || config.Ny < 4 ||
        config.fov_x_deg == 0) {
      Fail("lens model '", name,
           "': a splined model needs order 2 or 3, a control grid of at least 4 x 4 and a "
           "field of view above 0 degrees");
    }
  }
}

SolverEnd JudgeSolverEnd(const Eigen::SparseMatrix<double>& jt, const Eigen::VectorXd& x,
                         double rms_px) {
  SolverEnd end;
  if (!(rms_px >= 0) || !std::isfinite(rms_px) || !x.allFinite()) return end;
  end.cost = x.squaredNorm();
  end.termination = Termination::kConvergence;
  if (jt.rows() == 0 || !(end.cost > 0)) return end;
  const Eigen::VectorXd gradient = jt * x;
  const Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt(
      jt * Eigen::SparseMatrix<double>(jt.transpose()));
  if (ldlt.info() != Eigen::Success) return end;  // singular: the uncertainty says so
  // The Gauss-Newton model's drop |x|^2 - |x + J step|^2 = g^t inv(J^t J) g.
  end.expected_decrease = gradient.dot(ldlt.solve(gradient)) / end.cost;
  if (!(end.expected_decrease <= kCostTolerance)) end.termination = Termination::kNoConvergence;
  return end;
}

}  // namespace calibration_internal

namespace {

using calibration_internal::SolverEnd;

mrcal_pose_t ToMrcal(const Pose& pose) {
  const Rt rt = RtFromPose(pose);
  mrcal_pose_t out;
  for (int k = 0; k < 3; ++k) {
    out.r.xyz[k] = rt[k];
    out.t.xyz[k] = rt[3 + k];
  }
  return out;
}

Pose FromMrcal(const mrcal_pose_t& pose) {
  return PoseFromRt({pose.r.x, pose.r.y, pose.r.z, pose.t.x, pose.t.y, pose.t.z});
}

mrcal_lensmodel_t ParseModel(const std::string& name) {
  mrcal_lensmodel_t model;
  if (!mrcal_lensmodel_from_name(&model, name.c_str()) ||
      !mrcal_lensmodel_type_is_valid(model.type)) {
    Fail("unknown or unconfigured lens model '", name, "'");
  }
  return model;
}

bool IsSplined(const std::string& name) {
  return name.rfind("LENSMODEL_SPLINED_STEREOGRAPHIC", 0) == 0;
}

// The model that can represent every requested one: splined beats OPENCV12 beats OPENCV8 ...
std::string MostGeneralModel(const std::vector<std::string>& names) {
  auto rank = [](const std::string& n) {
    if (IsSplined(n)) return 10;
    if (n == "LENSMODEL_OPENCV12") return 6;
    if (n == "LENSMODEL_OPENCV8") return 5;
    if (n == "LENSMODEL_OPENCV5") return 4;
    if (n == "LENSMODEL_OPENCV4") return 3;
    if (n == "LENSMODEL_STEREOGRAPHIC") return 2;
    return 1;
  };
  std::string best = names.front();
  for (const auto& n : names) {
    if (rank(n) > rank(best)) best = n;
  }
  return best;
}

// The problem as mrcal sees it; the state lives here between stages.
struct Problem {
  BoardLayout layout;
  int width_n = 0, height_n = 0;
  std::vector<int> camera_index;  // mrcal camera -> index into the caller's cameras
  std::vector<int> imagersizes;   // 2 per mrcal camera
  std::vector<mrcal_observation_board_t> observations;
  std::vector<mrcal_point3_t> pool;     // Nobservations * height_n * width_n
  std::vector<int> observation_source;  // mrcal observation -> caller's observation index
  std::vector<int64_t> frame_sets;      // mrcal frame -> frame-set index
  std::string lensmodel;
  mrcal_lensmodel_t parsed{};
  std::vector<double> intrinsics;        // Ncameras * Nparams
  std::vector<mrcal_pose_t> extrinsics;  // cam_from_ref of the cameras away from the reference
  std::vector<int> extrinsics_of;        // mrcal camera -> index into extrinsics, -1: reference
  std::vector<mrcal_pose_t> frames;
  mrcal_calobject_warp_t warp{};
  mrcal_problem_selections_t selections{};
  mrcal_problem_constants_t constants{};
  std::vector<double> x;  // last residuals

  int ncams() const { return static_cast<int>(camera_index.size()); }
  int next() const { return static_cast<int>(extrinsics.size()); }
  Pose CamFromRef(int icam) const {
    return extrinsics_of[icam] < 0 ? Pose::Identity() : FromMrcal(extrinsics[extrinsics_of[icam]]);
  }
  int nparams() const { return mrcal_lensmodel_num_params(&parsed); }
  int nmeasurements() const {
    return mrcal_num_measurements(static_cast<int>(observations.size()), 0, width_n, height_n,
                                  ncams(), next(), static_cast<int>(frames.size()), 0, 0,
                                  selections, &parsed);
  }
  int nstate() const {
    return mrcal_num_states(ncams(), next(), static_cast<int>(frames.size()), 0, 0,
                            static_cast<int>(observations.size()), selections, &parsed);
  }

  void SetModel(const std::string& name) {
    lensmodel = name;
    parsed = ParseModel(name);
  }

  mrcal_stats_t Optimize(bool verbose) {
    x.assign(nmeasurements(), 0.0);
    return mrcal_optimize(
        nullptr, 0, x.data(), static_cast<int>(x.size() * sizeof(double)), intrinsics.data(),
        extrinsics.empty() ? nullptr : extrinsics.data(), frames.data(), nullptr,
        selections.do_optimize_calobject_warp ? &warp : nullptr, ncams(), next(),
        static_cast<int>(frames.size()), 0, 0, observations.data(), nullptr,
        static_cast<int>(observations.size()), 0, pool.data(), &parsed, imagersizes.data(),
        selections, &constants, layout.spacing, width_n, height_n, verbose, false);
  }
};

// The model of the joint solve: the most general one of the cameras that do not ask for a
// splined model when those are at least half the rig (a splined model for every camera is
// slow and needs many views), otherwise the most general of all.
std::string JointModel(const std::vector<std::string>& names) {
  std::vector<std::string> plain;
  for (const auto& n : names) {
    if (!IsSplined(n)) plain.push_back(n);
  }
  return 2 * plain.size() >= names.size() && !plain.empty() ? MostGeneralModel(plain)
                                                            : MostGeneralModel(names);
}

// Whether a camera asking for `requested` is served by the joint solve in `joint`: a splined
// model stands in for any other, an OPENCV model for any less general one.
bool Represents(const std::string& joint, const std::string& requested) {
  if (IsSplined(joint) || joint == requested) return true;
  auto opencv = [](const std::string& m) {
    return m.rfind("LENSMODEL_OPENCV", 0) == 0 || m == "LENSMODEL_PINHOLE";
  };
  return opencv(joint) && opencv(requested) && MostGeneralModel({joint, requested}) == joint;
}

// The problem `q` of one camera seen from the camera itself (no extrinsics, its board poses
// free): the state its projection uncertainty is propagated through, as a single-camera
// calibration would (the board poses it was solved against are not held fixed here).
Problem CameraFrame(const Problem& q) {
  Problem mono = q;
  for (auto& frame : mono.frames) frame = ToMrcal(q.CamFromRef(0) * FromMrcal(frame));
  mono.extrinsics.clear();
  mono.extrinsics_of = {-1};
  for (auto& obs : mono.observations) obs.icam.extrinsics = -1;
  mono.selections.do_optimize_extrinsics = false;
  mono.selections.do_optimize_frames = true;
  return mono;
}

// Camera m of the joint problem alone: its own views, the joint solve's board poses (held
// fixed) and its pose relative to the reference as the seed. `pool` holds the observations'
// weights as given, before the joint solve's outlier rejection.
Problem CameraAlone(const Problem& p, int m, const std::vector<mrcal_point3_t>& pool) {
  Problem q;
  q.layout = p.layout;
  q.width_n = p.width_n;
  q.height_n = p.height_n;
  q.camera_index = {p.camera_index[m]};
  q.imagersizes = {p.imagersizes[2 * static_cast<size_t>(m)],
                   p.imagersizes[2 * static_cast<size_t>(m) + 1]};
  if (p.extrinsics_of[m] >= 0) q.extrinsics.push_back(p.extrinsics[p.extrinsics_of[m]]);
  q.extrinsics_of = {q.extrinsics.empty() ? -1 : 0};
  const size_t per_view = static_cast<size_t>(p.width_n) * p.height_n;
  std::map<int, int> frame_of;
  for (size_t o = 0; o < p.observations.size(); ++o) {
    if (p.observations[o].icam.intrinsics != m) continue;
    const int iframe = p.observations[o].iframe;
    const auto [it, inserted] = frame_of.emplace(iframe, static_cast<int>(q.frames.size()));
    if (inserted) {
      q.frames.push_back(p.frames[iframe]);
      q.frame_sets.push_back(p.frame_sets[iframe]);
    }
    mrcal_observation_board_t obs = p.observations[o];
    obs.icam.intrinsics = 0;
    obs.icam.extrinsics = q.extrinsics_of[0];
    obs.iframe = it->second;
    q.observations.push_back(obs);
    q.observation_source.push_back(p.observation_source[o]);
    q.pool.insert(q.pool.end(), pool.begin() + o * per_view, pool.begin() + (o + 1) * per_view);
  }
  return q;
}

mrcal_problem_selections_t Selections(bool core, bool distortions, bool regularization,
                                      bool outliers, bool warp) {
  mrcal_problem_selections_t s{};
  s.do_optimize_intrinsics_core = core;
  s.do_optimize_intrinsics_distortions = distortions;
  s.do_optimize_extrinsics = true;
  s.do_optimize_frames = true;
  s.do_optimize_calobject_warp = warp;
  s.do_apply_regularization = regularization;
  s.do_apply_outlier_rejection = outliers;
  return s;
}

// A pinhole-free seed of one view: the observed pixels are unprojected through a
// stereographic lens of focal `focal` (valid beyond 90 degrees, unlike a pinhole), put on the
// z = 1 plane and handed to solvePnP with an identity camera matrix.
bool SeedView(const BoardObservation& obs, const Board& board, double focal, double cx, double cy,
              Pose* cam_from_board) {
  std::vector<cv::Point3d> object;
  std::vector<cv::Point2d> normalised;
  const int width_n = board.width_n();
  for (int r = 0; r < obs.points.rows(); ++r) {
    if (obs.points(r, 2) <= 0) continue;
    mrcal_point2_t q{{obs.points(r, 0), obs.points(r, 1)}};
    mrcal_point3_t v;
    const double fxycxy[4] = {focal, focal, cx, cy};
    mrcal_unproject_stereographic(&v, nullptr, &q, 1, fxycxy);
    if (v.z < 0.2 * std::hypot(v.x, v.y)) continue;  // beyond ~80 degrees: pinhole breaks down
    const Eigen::Vector3d p = board.GridPoint(r % width_n, r / width_n);
    object.emplace_back(p.x(), p.y(), p.z());
    normalised.emplace_back(v.x / v.z, v.y / v.z);
  }
  if (object.size() < 6) return false;
  cv::Mat rvec, tvec;
  std::vector<int> inliers;
  const cv::Mat K = cv::Mat::eye(3, 3, CV_64F);
  if (!cv::solvePnPRansac(object, normalised, K, cv::noArray(), rvec, tvec, false, 200, 8.0 / focal,
                          0.99, inliers, cv::SOLVEPNP_IPPE) ||
      inliers.size() < 6) {
    return false;
  }
  std::vector<cv::Point3d> object_in;
  std::vector<cv::Point2d> normalised_in;
  for (int k : inliers) {
    object_in.push_back(object[k]);
    normalised_in.push_back(normalised[k]);
  }
  cv::solvePnPRefineLM(object_in, normalised_in, K, cv::noArray(), rvec, tvec);
  *cam_from_board = PoseFromRt({rvec.at<double>(0), rvec.at<double>(1), rvec.at<double>(2),
                                tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2)});
  return cam_from_board->translation().z() > 0;
}

// Focal length from the board views' homographies (OpenCV's closed form), in pinhole terms.
double SeedFocal(const std::vector<const BoardObservation*>& views, const Board& board, int width,
                 int height) {
  std::vector<std::vector<cv::Point3f>> object;
  std::vector<std::vector<cv::Point2f>> image;
  const int width_n = board.width_n();
  for (const BoardObservation* obs : views) {
    std::vector<cv::Point3f> o;
    std::vector<cv::Point2f> i;
    for (int r = 0; r < obs->points.rows(); ++r) {
      if (obs->points(r, 2) <= 0) continue;
      const Eigen::Vector3d p = board.GridPoint(r % width_n, r / width_n);
      o.emplace_back(static_cast<float>(p.x()), static_cast<float>(p.y()), 0.f);
      i.emplace_back(static_cast<float>(obs->points(r, 0)), static_cast<float>(obs->points(r, 1)));
    }
    if (o.size() >= 6) {
      object.push_back(o);
      image.push_back(i);
    }
  }
  double focal = 0;
  if (!object.empty()) {
    const cv::Mat K = cv::initCameraMatrix2D(object, image, cv::Size(width, height));
    focal = 0.5 * (K.at<double>(0, 0) + K.at<double>(1, 1));
  }
  if (!std::isfinite(focal) || focal < 0.1 * width || focal > 20.0 * width) focal = 0.8 * width;
  return focal;
}

// Median reprojection error (pixels) of a seeded view through the stereographic seed lens.
double SeedViewError(const BoardObservation& obs, const Board& board, double focal, double cx,
                     double cy, const Pose& cam_from_board) {
  std::vector<double> errors;
  const double fxycxy[4] = {focal, focal, cx, cy};
  for (int r = 0; r < obs.points.rows(); ++r) {
    if (obs.points(r, 2) <= 0) continue;
    const Eigen::Vector3d p =
        cam_from_board * board.GridPoint(r % board.width_n(), r / board.width_n());
    mrcal_point3_t pm{{p.x(), p.y(), p.z()}};
    mrcal_point2_t q;
    mrcal_project_stereographic(&q, nullptr, &pm, 1, fxycxy);
    errors.push_back(std::hypot(q.x - obs.points(r, 0), q.y - obs.points(r, 1)));
  }
  if (errors.empty()) return 1e9;
  std::nth_element(errors.begin(), errors.begin() + errors.size() / 2, errors.end());
  return errors[errors.size() / 2];
}

double WorstDirectionSigma(const Eigen::Matrix2d& cov) {
  const double a = cov(0, 0), b = cov(1, 0), c = cov(1, 1);
  return std::sqrt((a + c) / 2 + std::sqrt((a - c) * (a - c) / 4 + b * b));
}

// The Jacobian of the final solve from mrcal_optimizer_callback (packed, unitless state),
// as Jt: Nstate x Nmeasurements.
bool Jacobian(Problem& p, Eigen::SparseMatrix<double>* jt) {
  cholmod_common common;
  if (!cholmod_start(&common)) return false;
  const int nstate = p.nstate();
  const int nmeas = p.nmeasurements();
  const int nnz =
      _mrcal_num_j_nonzero(static_cast<int>(p.observations.size()), 0, p.width_n, p.height_n,
                           p.ncams(), p.next(), static_cast<int>(p.frames.size()), 0, 0,
                           p.observations.data(), nullptr, p.selections, &p.parsed);
  cholmod_sparse* sparse =
      cholmod_allocate_sparse(nstate, nmeas, nnz, 1, 1, 0, CHOLMOD_REAL, &common);
  if (sparse == nullptr) {
    cholmod_finish(&common);
    return false;
  }
  std::vector<double> b(nstate), x(nmeas);
  const bool ok = mrcal_optimizer_callback(
      b.data(), static_cast<int>(nstate * sizeof(double)), x.data(),
      static_cast<int>(nmeas * sizeof(double)), reinterpret_cast<cholmod_sparse_struct*>(sparse),
      p.intrinsics.data(), p.extrinsics.empty() ? nullptr : p.extrinsics.data(), p.frames.data(),
      nullptr, p.selections.do_optimize_calobject_warp ? &p.warp : nullptr, p.ncams(), p.next(),
      static_cast<int>(p.frames.size()), 0, 0, p.observations.data(), nullptr,
      static_cast<int>(p.observations.size()), 0, p.pool.data(), &p.parsed, p.imagersizes.data(),
      p.selections, &p.constants, p.layout.spacing, p.width_n, p.height_n, false);
  if (ok) {
    const int* col = static_cast<const int*>(sparse->p);
    const int* row = static_cast<const int*>(sparse->i);
    const double* value = static_cast<const double*>(sparse->x);
    std::vector<Eigen::Triplet<double>> triplets;
    triplets.reserve(col[nmeas]);
    for (int c = 0; c < nmeas; ++c) {
      for (int k = col[c]; k < col[c + 1]; ++k) triplets.emplace_back(row[k], c, value[k]);
    }
    jt->resize(nstate, nmeas);
    jt->setFromTriplets(triplets.begin(), triplets.end());
  }
  cholmod_free_sparse(&sparse, &common);
  cholmod_finish(&common);
  return ok;
}

// How mrcal's solve of `p` ended. mrcal 2.2's mrcal_optimize returns only mrcal_stats_t: the
// RMS (negative when it could not run) and the outlier count. libdogleg's own ending (its step
// below 1e-6, or the 300 iterations mrcal_optimize allows spent) and its iteration count are
// printed only with verbose, never returned; so the ending is judged at mrcal's result, from
// mrcal's own residuals and mrcal_optimizer_callback's Jacobian there.
SolverEnd JudgeEnd(Problem& p, const mrcal_stats_t& stats) {
  const Eigen::VectorXd x =
      Eigen::Map<const Eigen::VectorXd>(p.x.data(), static_cast<Eigen::Index>(p.x.size()));
  const double rms = stats.rms_reproj_error__pixels;
  Eigen::SparseMatrix<double> jt;
  if (rms >= 0 && std::isfinite(rms) && !Jacobian(p, &jt)) jt.resize(0, 0);
  return calibration_internal::JudgeSolverEnd(jt, x, rms);
}

// d(transform_point_rt(rt, x))/d(rt) and /d(x).
void TransformGradients(const mrcal_pose_t& pose, const Eigen::Vector3d& x, Eigen::Vector3d* out,
                        Eigen::Matrix<double, 3, 6, Eigen::RowMajor>* d_rt,
                        Eigen::Matrix<double, 3, 3, Eigen::RowMajor>* d_x) {
  double rt[6] = {pose.r.x, pose.r.y, pose.r.z, pose.t.x, pose.t.y, pose.t.z};
  double xin[3] = {x.x(), x.y(), x.z()};
  double xout[3];
  mrcal_transform_point_rt(xout, d_rt ? d_rt->data() : nullptr, d_x ? d_x->data() : nullptr, rt,
                           xin);
  *out << xout[0], xout[1], xout[2];
}

Eigen::Vector3d InvertTransform(const mrcal_pose_t& pose, const Eigen::Vector3d& x) {
  double rt[6] = {pose.r.x, pose.r.y, pose.r.z, pose.t.x, pose.t.y, pose.t.z};
  double xin[3] = {x.x(), x.y(), x.z()};
  double xout[3];
  mrcal_transform_point_rt_inverted(xout, nullptr, nullptr, rt, xin);
  return Eigen::Vector3d(xout[0], xout[1], xout[2]);
}

struct Factorization {
  Eigen::SparseMatrix<double> jt;  // packed
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> ldlt;
  Eigen::SparseMatrix<double> jobs_t_jobs;  // the observations' share of J*tJ*
  int nmeas_observations = 0;
  bool regularized = false;
  // Jobs^t Jobs alone (regularised problems): what the views constrain without the
  // regularisation's pull, which holds parameters no view fixes at its prior.
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<double>> views_only;
};

// The solve's J*tJ* factored for the noise propagation.
bool Factor(Problem& p, Factorization* f) {
  if (!Jacobian(p, &f->jt)) return false;
  const Eigen::SparseMatrix<double> jtj = f->jt * Eigen::SparseMatrix<double>(f->jt.transpose());
  f->ldlt.compute(jtj);
  if (f->ldlt.info() != Eigen::Success) return false;
  f->nmeas_observations =
      mrcal_num_measurements_boards(static_cast<int>(p.observations.size()), p.width_n, p.height_n);
  f->regularized = f->nmeas_observations != p.nmeasurements();
  if (f->regularized) {
    const Eigen::SparseMatrix<double> jobs_t = f->jt.leftCols(f->nmeas_observations);
    f->jobs_t_jobs = jobs_t * Eigen::SparseMatrix<double>(jobs_t.transpose());
    f->views_only.compute(f->jobs_t_jobs);
  }
  return true;
}

// Where camera `icam`'s parameters sit in the solve's state (-1: not optimised).
struct CameraState {
  int intrinsics = -1;
  int first_optimized = 0;  // first intrinsic in the state (4 when the core is held fixed)
  int extrinsics = -1;
  int frames = -1;  // the first board pose
};

CameraState StateOf(Problem& p, int icam) {
  const int nframes = static_cast<int>(p.frames.size());
  const int nobs = static_cast<int>(p.observations.size());
  CameraState state;
  state.intrinsics = mrcal_state_index_intrinsics(icam, p.ncams(), p.next(), nframes, 0, 0, nobs,
                                                  p.selections, &p.parsed);
  const int extr = p.extrinsics_of[icam];
  if (extr >= 0 && p.selections.do_optimize_extrinsics) {
    state.extrinsics = mrcal_state_index_extrinsics(extr, p.ncams(), p.next(), nframes, 0, 0, nobs,
                                                    p.selections, &p.parsed);
  }
  // Board poses held fixed (a camera re-solved alone) carry no uncertainty of their own here.
  if (p.selections.do_optimize_frames) {
    state.frames = mrcal_state_index_frames(0, p.ncams(), p.next(), nframes, 0, 0, nobs,
                                            p.selections, &p.parsed);
  }
  const bool has_core = mrcal_lensmodel_metadata(&p.parsed).has_core;
  state.first_optimized = has_core && !p.selections.do_optimize_intrinsics_core ? 4 : 0;
  return state;
}

// Covariance of functions of the state whose gradients (by the unpacked state) are the
// columns of `gradients`, propagated from the observation noise like the projections.
// `views_only`: from the views alone, without the regularisation (Jobs^t Jobs inverted).
Eigen::MatrixXd StateCovariance(Problem& p, Factorization& f, Eigen::MatrixXd gradients,
                                double sigma, bool views_only = false) {
  for (int c = 0; c < gradients.cols(); ++c) {
    Eigen::VectorXd column = gradients.col(c);
    mrcal_unpack_solver_state_vector(column.data(), p.ncams(), p.next(),
                                     static_cast<int>(p.frames.size()), 0, 0, p.selections,
                                     &p.parsed);
    gradients.col(c) = column;
  }
  if (views_only && f.regularized && f.views_only.info() != Eigen::Success) {
    return Eigen::MatrixXd::Constant(gradients.cols(), gradients.cols(),
                                     std::numeric_limits<double>::infinity());
  }
  if (views_only) {
    // Singular where the views leave a direction free: its variance is then huge or not finite.
    const Eigen::MatrixXd a =
        f.regularized ? Eigen::MatrixXd(f.views_only.solve(gradients)) : f.ldlt.solve(gradients);
    return gradients.transpose() * a * sigma * sigma;
  }
  const Eigen::MatrixXd a = f.ldlt.solve(gradients);
  const Eigen::MatrixXd b = f.regularized ? Eigen::MatrixXd(f.jobs_t_jobs * a) : gradients;
  return b.transpose() * a * sigma * sigma;
}

// The 1-sigma of camera `icam`'s intrinsics and of its pose relative to the reference.
void ParameterSigma(Problem& p, Factorization& f, int icam, double sigma, CalibratedCamera* out) {
  const CameraState state = StateOf(p, icam);
  const int nparams = p.nparams();
  const int nstate = p.nstate();
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  out->intrinsics_sigma.assign(nparams, kNaN);
  if (state.intrinsics >= 0) {
    const int k = nparams - state.first_optimized;
    Eigen::MatrixXd gradients = Eigen::MatrixXd::Zero(nstate, k);
    for (int c = 0; c < k; ++c) gradients(state.intrinsics + c, c) = 1;
    const Eigen::MatrixXd cov = StateCovariance(p, f, gradients, sigma);
    for (int c = 0; c < k; ++c)
      out->intrinsics_sigma[state.first_optimized + c] = std::sqrt(cov(c, c));
    if (state.first_optimized == 0 && mrcal_lensmodel_metadata(&p.parsed).has_core) {
      const Eigen::MatrixXd alone =
          StateCovariance(p, f, gradients.leftCols(2), sigma, /*views_only=*/true);
      const double* intrinsics = p.intrinsics.data() + static_cast<ptrdiff_t>(icam) * nparams;
      // Without the regularisation a lens with many distortion terms (OPENCV8) is often
      // singular however well its views spread: a 640 px studio8 board take's camera, 0.25 %
      // from the true focal length, factors no better. A figure that cannot be computed decides
      // nothing (NaN); the pose spread and the regularised projection uncertainty judge then.
      double worst = 0;
      for (int c = 0; c < 2; ++c) {
        const double relative = std::sqrt(alone(c, c)) / std::abs(intrinsics[c]);
        worst = std::isfinite(relative) ? std::max(worst, relative) : kNaN;
        if (std::isnan(worst)) break;
      }
      out->focal_sigma_views_rel = worst;
    }
  }
  if (state.extrinsics < 0) return;
  // Rotation (the rt's r, radians) and camera centre -R^t t (numeric derivatives by rt).
  const mrcal_pose_t& pose = p.extrinsics[p.extrinsics_of[icam]];
  const Rt rt = RtFromPose(FromMrcal(pose));
  Eigen::MatrixXd gradients = Eigen::MatrixXd::Zero(nstate, 6);
  for (int c = 0; c < 3; ++c) gradients(state.extrinsics + c, c) = 1;
  for (int d = 0; d < 6; ++d) {
    Rt plus = rt, minus = rt;
    plus[d] += 1e-7;
    minus[d] -= 1e-7;
    const Eigen::Vector3d dc =
        (PoseFromRt(plus).inverse().translation() - PoseFromRt(minus).inverse().translation()) /
        2e-7;
    for (int r = 0; r < 3; ++r) gradients(state.extrinsics + d, 3 + r) = dc(r);
  }
  const Eigen::MatrixXd cov = StateCovariance(p, f, gradients, sigma);
  const Eigen::Matrix3d rotation = cov.topLeftCorner<3, 3>(),
                        center = cov.bottomRightCorner<3, 3>();
  out->rotation_sigma_deg =
      std::sqrt(Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(rotation).eigenvalues().maxCoeff()) *
      180 / std::numbers::pi;
  out->center_sigma_mm =
      1000 *
      std::sqrt(Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(center).eigenvalues().maxCoeff());
}

// mrcal's projection_uncertainty(): Var(q) for pixels of camera `icam` at `distance`.
CameraUncertainty Uncertainty(Problem& p, Factorization& f, int icam, double distance, double sigma,
                              int grid_x, int grid_y) {
  CameraUncertainty u;
  u.grid_x = grid_x;
  u.grid_y = grid_y;
  u.distance_m = distance;
  const int width = p.imagersizes[2 * static_cast<size_t>(icam)],
            height = p.imagersizes[2 * static_cast<size_t>(icam) + 1];
  const int n = grid_x * grid_y;
  u.pixels.resize(2, n);
  for (int gy = 0; gy < grid_y; ++gy) {
    for (int gx = 0; gx < grid_x; ++gx) {
      u.pixels.col(gy * grid_x + gx) << (gx + 0.5) * width / grid_x - 0.5,
          (gy + 0.5) * height / grid_y - 0.5;
    }
  }
  const int nparams = p.nparams();
  const double* intrinsics = p.intrinsics.data() + static_cast<ptrdiff_t>(icam) * nparams;
  const int nstate = p.nstate();
  const int nframes = static_cast<int>(p.frames.size());
  const CameraState state = StateOf(p, icam);
  const int i_intr = state.intrinsics, i_extr = state.extrinsics, i_frames = state.frames;
  const int extr = p.extrinsics_of[icam];
  const int first_optimized = state.first_optimized;

  u.covariance.assign(n, Eigen::Matrix2d::Constant(std::numeric_limits<double>::quiet_NaN()));
  u.worst_sigma_px =
      Eigen::MatrixXd::Constant(grid_y, grid_x, std::numeric_limits<double>::quiet_NaN());
  const int chunk = 16;
  for (int start = 0; start < n; start += chunk) {
    const int count = std::min(chunk, n - start);
    Eigen::MatrixXd dq_db =
        Eigen::MatrixXd::Zero(nstate, Eigen::Index{2} * count);  // columns: (dq/db*)^t
    std::vector<bool> valid(count, true);
    for (int k = 0; k < count; ++k) {
      mrcal_point2_t q{{u.pixels(0, start + k), u.pixels(1, start + k)}};
      mrcal_point3_t v;
      if (!mrcal_unproject(&v, &q, 1, &p.parsed, intrinsics) || !std::isfinite(v.x)) {
        valid[k] = false;
        continue;
      }
      Eigen::Vector3d p_cam(v.x, v.y, v.z);
      p_cam = p_cam.normalized() * distance;
      mrcal_point3_t pc{{p_cam.x(), p_cam.y(), p_cam.z()}};
      mrcal_point2_t q2;
      mrcal_point3_t dq_dp[2];
      std::vector<double> dq_dintr(2 * static_cast<size_t>(nparams));
      if (!mrcal_project(&q2, dq_dp, dq_dintr.data(), &pc, 1, &p.parsed, intrinsics)) {
        valid[k] = false;
        continue;
      }
      Eigen::Matrix<double, 2, 3> dq_dpcam;
      for (int r = 0; r < 2; ++r) {
        for (int c = 0; c < 3; ++c) dq_dpcam(r, c) = dq_dp[r].xyz[c];
      }
      Eigen::MatrixXd rows = Eigen::MatrixXd::Zero(2, nstate);
      if (i_intr >= 0) {
        for (int r = 0; r < 2; ++r) {
          for (int c = first_optimized; c < nparams; ++c) {
            rows(r, i_intr + c - first_optimized) = dq_dintr[r * nparams + c];
          }
        }
      }
      Eigen::Vector3d p_ref = p_cam;
      Eigen::Matrix3d dpcam_dpref = Eigen::Matrix3d::Identity();
      if (extr >= 0) {
        p_ref = InvertTransform(p.extrinsics[extr], p_cam);
        Eigen::Vector3d check;
        Eigen::Matrix<double, 3, 6, Eigen::RowMajor> d_rt;
        Eigen::Matrix<double, 3, 3, Eigen::RowMajor> d_x;
        TransformGradients(p.extrinsics[extr], p_ref, &check, &d_rt, &d_x);
        if (i_extr >= 0) rows.block(0, i_extr, 2, 6) = dq_dpcam * d_rt;
        dpcam_dpref = d_x;
      }
      // The point as each board pose sees it, mapped back and averaged: its sensitivity to
      // every frame, divided by Nframes.
      const Eigen::Matrix<double, 2, 3> dq_dpref = dq_dpcam * dpcam_dpref;
      for (int fr = 0; fr < nframes && i_frames >= 0; ++fr) {
        const Eigen::Vector3d p_frame = InvertTransform(p.frames[fr], p_ref);
        Eigen::Vector3d back;
        Eigen::Matrix<double, 3, 6, Eigen::RowMajor> d_rt;
        TransformGradients(p.frames[fr], p_frame, &back, &d_rt, nullptr);
        rows.block(0, i_frames + 6 * fr, 2, 6) = dq_dpref * d_rt / nframes;
      }
      // To the packed state: the state is in the denominator, so "unpack" scales it.
      for (int r = 0; r < 2; ++r) {
        Eigen::VectorXd row = rows.row(r).transpose();
        mrcal_unpack_solver_state_vector(row.data(), p.ncams(), p.next(), nframes, 0, 0,
                                         p.selections, &p.parsed);
        dq_db.col(2 * k + r) = row;
      }
    }
    const Eigen::MatrixXd a = f.ldlt.solve(dq_db);  // inv(J*tJ*) D dF/db^t
    // Regularised: A^t (Jobs^t Jobs) A; otherwise the observations are all of J and
    // A^t (J^t J) A collapses to dF/db D A.
    const Eigen::MatrixXd b = f.regularized ? Eigen::MatrixXd(f.jobs_t_jobs * a) : dq_db;
    for (int k = 0; k < count; ++k) {
      if (!valid[k]) continue;
      const Eigen::Matrix2d cov = b.middleCols(Eigen::Index{2} * k, 2).transpose() *
                                  a.middleCols(Eigen::Index{2} * k, 2) * sigma * sigma;
      u.covariance[start + k] = cov;
      const int index = start + k;
      u.worst_sigma_px(index / grid_x, index % grid_x) = WorstDirectionSigma(cov);
    }
  }
  double worst = 0, sum = 0;
  int counted = 0;
  bool finite = true;
  for (int k = 0; k < n; ++k) {
    const double s = u.worst_sigma_px(k / grid_x, k % grid_x);
    if (!std::isfinite(s)) {
      finite = false;
      continue;
    }
    worst = std::max(worst, s);
    sum += s;
    ++counted;
  }
  u.worst_px = finite ? worst : std::numeric_limits<double>::infinity();
  u.mean_px = counted > 0 ? sum / counted : std::numeric_limits<double>::infinity();
  return u;
}

}  // namespace

void CalibrationOptions::Check() const {
  HOLOCAP_CHECK_OPTION_GE(min_views_per_camera, 3);
  HOLOCAP_CHECK_OPTION_GE(min_points_per_view, 4);
  HOLOCAP_CHECK_OPTION_GE(tag_read_px, 0, "0: DetectionOptions::min_tag_side_px's default");
  HOLOCAP_CHECK_OPTION_GT(max_seed_rms_px, 0);
  HOLOCAP_CHECK_OPTION_IN(max_order_disagreement_deg, 1, 45,
                          "a numbering a quarter turn away differs by 90 degrees");
  HOLOCAP_CHECK_OPTION_GT(max_cross_validation_ratio, 0);
  HOLOCAP_CHECK_OPTION_GE(uncertainty_grid_x, 2);
  HOLOCAP_CHECK_OPTION_GE(uncertainty_grid_y, 2);
  HOLOCAP_CHECK_OPTION_GE(uncertainty_distance_m, 0, "0: automatic");
  HOLOCAP_CHECK_OPTION_GE(observed_pixel_sigma, 0, "0: from the residuals");
  HOLOCAP_CHECK_OPTION_GT(max_uncertainty_px, 0);
  HOLOCAP_CHECK_OPTION_GT(max_focal_sigma_rel, 0);
  HOLOCAP_CHECK_OPTION_GE(min_normal_spread_deg, 0);
  HOLOCAP_CHECK_OPTION_GE(max_residual_to_noise, 1, "an adequate model's RMS is the noise");
}

nlohmann::json CalibrationOptions::ToJson() const {
  return {{"reference_camera", reference_camera},
          {"min_views_per_camera", min_views_per_camera},
          {"min_points_per_view", min_points_per_view},
          {"regularization", regularization},
          {"outlier_rejection", outlier_rejection},
          {"solve_board_warp", solve_board_warp},
          {"tag_read_px", tag_read_px},
          {"max_seed_rms_px", max_seed_rms_px},
          {"max_order_disagreement_deg", max_order_disagreement_deg},
          {"uncertainty", uncertainty},
          {"uncertainty_grid", {uncertainty_grid_x, uncertainty_grid_y}},
          {"uncertainty_distance_m", uncertainty_distance_m},
          {"observed_pixel_sigma", observed_pixel_sigma},
          {"max_uncertainty_px", max_uncertainty_px},
          {"max_focal_sigma_rel", max_focal_sigma_rel},
          {"min_normal_spread_deg", min_normal_spread_deg},
          {"check_model_fit", check_model_fit},
          {"max_residual_to_noise", max_residual_to_noise},
          {"cross_validation", cross_validation},
          {"max_cross_validation_ratio", max_cross_validation_ratio}};
}

nlohmann::json PoseSpread::ToJson() const {
  return {{"tilt_min_deg", tilt_min_deg},           {"tilt_max_deg", tilt_max_deg},
          {"normal_spread_deg", normal_spread_deg}, {"distance_min_m", distance_min_m},
          {"distance_max_m", distance_max_m},       {"coverage", coverage}};
}

const CalibratedCamera* CalibrationSummary::Find(const std::string& name) const {
  for (const auto& c : cameras) {
    if (c.name == name) return &c;
  }
  return nullptr;
}

nlohmann::json CalibrationSummary::ToJson() const {
  nlohmann::json cams = nlohmann::json::object();
  for (const auto& c : cameras) {
    nlohmann::json j = {{"solved", c.solved},
                        {"flag", c.flag},
                        {"views", c.views},
                        {"points", c.points},
                        {"outliers", c.outliers},
                        {"rms_px", c.rms_px},
                        {"median_board_distance_m", c.median_board_distance_m},
                        {"pose_spread", c.pose_spread.ToJson()}};
    j["feature_side_px"] = nullptr;
    if (std::isfinite(c.feature_side_px_median)) {
      j["feature_side_px"] = {{"min", c.feature_side_px_min}, {"median", c.feature_side_px_median}};
    }
    if (c.solved) {
      j["lensmodel"] = c.model.lensmodel();
      j["intrinsics"] = c.model.intrinsics();
      j["rt_cam_ref"] = RtFromPose(c.model.cam_from_world());
      if (!c.intrinsics_sigma.empty()) {
        // NaN (a parameter held fixed, the reference camera's pose) is written as null.
        j["intrinsics_sigma"] = c.intrinsics_sigma;
        j["rotation_sigma_deg"] = c.rotation_sigma_deg;
        j["center_sigma_mm"] = c.center_sigma_mm;
        j["focal_sigma_views_rel"] = c.focal_sigma_views_rel;
      }
      if (c.uncertainty.grid_x > 0) {
        std::vector<std::vector<double>> grid;
        for (int y = 0; y < c.uncertainty.grid_y; ++y) {
          std::vector<double> row;
          row.reserve(c.uncertainty.grid_x);
          for (int x = 0; x < c.uncertainty.grid_x; ++x)
            row.push_back(c.uncertainty.worst_sigma_px(y, x));
          grid.push_back(row);
        }
        j["uncertainty"] = {{"worst_px", c.uncertainty.worst_px},
                            {"worst_observed_px", c.uncertainty.worst_observed_px},
                            {"mean_px", c.uncertainty.mean_px},
                            {"distance_m", c.uncertainty.distance_m},
                            {"grid", {c.uncertainty.grid_x, c.uncertainty.grid_y}},
                            {"worst_direction_sigma_px", grid}};
      }
    }
    cams[c.name] = j;
  }
  nlohmann::json stage_json = nlohmann::json::array();
  for (const auto& s : stages) {
    stage_json.push_back({{"stage", s.name},
                          {"lensmodel", s.lensmodel},
                          {"rms_px", s.rms_px},
                          {"outliers", s.outliers},
                          {"t_s", s.seconds},
                          {"termination", ToString(s.termination)},
                          {"cost", s.cost},
                          {"expected_decrease", s.expected_decrease}});
  }
  nlohmann::json dropped_json = nlohmann::json::array();
  for (const auto& d : dropped_views) {
    dropped_json.push_back(
        {{"sensor", d.sensor}, {"frame_set", d.frame_set}, {"reason", d.reason}});
  }
  nlohmann::json j = {
      {"termination", ToString(termination)},
      {"message", message},
      {"lensmodel", lensmodel},
      {"reference_camera", reference_camera},
      {"rms_reprojection_px", rms_reprojection_px},
      {"observed_pixel_sigma", observed_pixel_sigma},
      {"frames", frames},
      {"observations", observations},
      {"outliers", outliers},
      {"reordered_views", reordered_views},
      {"dropped_views", dropped_json},
      {"warnings", warnings},
      {"notes", notes},
      {"cameras", cams},
      {"stages", stage_json},
      {"model_fit", model_fit},
      {"board_warp_m", std::isfinite(board_warp_x_m)
                           ? nlohmann::json::array({board_warp_x_m, board_warp_y_m})
                           : nlohmann::json(nullptr)},
      {"timing", {{"solve_s", solve_seconds}, {"uncertainty_s", uncertainty_seconds}}}};
  for (const auto& s : stages) {
    if (s.name != "everything") continue;
    // mrcal's own figures of its final joint solve (mrcal 2.2 reports no iteration count).
    j["mrcal"] = {{"termination", ToString(s.termination)},
                  {"rms_px", s.rms_px},
                  {"outliers", s.outliers},
                  {"cost", s.cost},
                  {"expected_decrease", s.expected_decrease}};
  }
  if (!cross_validation.is_null()) j["cross_validation"] = cross_validation;
  return j;
}

namespace {

// The rigid motion b_from_a that best carries points of camera a onto the pixels camera b
// sees them at (Gauss-Newton on the pixel residuals, numeric derivatives, seeded by `seed`).
// A point-to-point fit of the two halves' points weighs range as much as direction, while
// what is compared is projections.
Pose FitImpliedTransform(const CameraModel& b, const std::vector<Eigen::Vector3d>& points_a,
                         const std::vector<Eigen::Vector2d>& pixels, const Pose& seed) {
  Rt rt = RtFromPose(seed);
  const int n = static_cast<int>(points_a.size());
  auto residuals = [&](const Rt& x, Eigen::VectorXd* r) {
    const Pose pose = PoseFromRt(x);
    r->resize(Eigen::Index{2} * n);
    for (int k = 0; k < n; ++k) {
      Eigen::Vector2d q;
      if (!b.Project(pose * points_a[k], &q)) return false;
      r->segment<2>(Eigen::Index{2} * k) = q - pixels[k];
    }
    return true;
  };
  Eigen::VectorXd r;
  if (!residuals(rt, &r)) return seed;
  for (int iteration = 0; iteration < 10; ++iteration) {
    Eigen::MatrixXd jacobian(2 * n, 6);
    bool ok = true;
    for (int d = 0; d < 6 && ok; ++d) {
      const double h = d < 3 ? 1e-7 : 1e-7 * std::max(1.0, points_a[0].norm());
      Rt plus = rt, minus = rt;
      plus[d] += h;
      minus[d] -= h;
      Eigen::VectorXd rp, rm;
      ok = residuals(plus, &rp) && residuals(minus, &rm);
      if (ok) jacobian.col(d) = (rp - rm) / (2 * h);
    }
    if (!ok) break;
    const Eigen::Matrix<double, 6, 1> step =
        (jacobian.transpose() * jacobian).ldlt().solve(-jacobian.transpose() * r);
    if (!step.allFinite()) break;
    Rt next = rt;
    for (int d = 0; d < 6; ++d) next[d] += step[d];
    Eigen::VectorXd r_next;
    if (!residuals(next, &r_next) || r_next.squaredNorm() >= r.squaredNorm()) break;
    rt = next;
    r = r_next;
    if (step.norm() < 1e-12) break;
  }
  return PoseFromRt(rt);
}

// Cross-validation: each half's models projected against the other's at the working
// distance, in each camera's own frame, set against the sum of the two 1-sigma estimates.
nlohmann::json CrossValidate(const CalibrationSummary& a, const CalibrationSummary& b) {
  nlohmann::json result = nlohmann::json::object();
  double worst_ratio = 0, worst_to_predicted = 0;
  for (const auto& ca : a.cameras) {
    const CalibratedCamera* cb = b.Find(ca.name);
    if (!ca.solved || cb == nullptr || !cb->solved || ca.uncertainty.grid_x == 0 ||
        cb->uncertainty.grid_x == 0) {
      continue;
    }
    // Like mrcal's projection_diff at a finite distance: the two halves' camera frames may
    // differ by a rigid motion that their intrinsics absorb (each half anchors its world to its
    // own mean of board poses), so the implied transform is fitted where the board was seen,
    // to the pixels of the points half a puts there, before the projections are compared at
    // the working distance.
    const Eigen::Matrix2Xd& pixels = ca.uncertainty.pixels;
    const double distance = ca.uncertainty.distance_m;
    const Eigen::Matrix3Xd rays = ca.model.UnprojectMany(pixels);
    const Eigen::Matrix3Xd rays_b = cb->model.UnprojectMany(pixels);
    // One distance lets a shift along the axis stand in for a focal-length change, so the
    // transform is fitted over half, one and twice the working distance together.
    std::vector<Eigen::Vector3d> points_a, points_b;
    std::vector<Eigen::Vector2d> seen_pixels;
    for (int k = 0; k < pixels.cols(); ++k) {
      const int gx = k % ca.uncertainty.grid_x, gy = k / ca.uncertainty.grid_x;
      if (!rays.col(k).allFinite() || !rays_b.col(k).allFinite()) continue;
      if (ca.uncertainty.observed.size() > 0 && !ca.uncertainty.observed(gy, gx)) continue;
      for (double scale : {0.5, 1.0, 2.0}) {
        points_a.push_back(rays.col(k).normalized() * distance * scale);
        points_b.push_back(rays_b.col(k).normalized() * distance * scale);
        seen_pixels.push_back(pixels.col(k));
      }
    }
    if (points_a.size() < 3) continue;
    const Pose b_from_a = FitImpliedTransform(cb->model, points_a, seen_pixels,
                                              calibration_internal::FitRigid(points_a, points_b));
    double sum2 = 0, worst = 0;
    int within = 0, n = 0;
    for (int k = 0; k < pixels.cols(); ++k) {
      if (!rays.col(k).allFinite()) continue;
      const int gx0 = k % ca.uncertainty.grid_x, gy0 = k / ca.uncertainty.grid_x;
      if (ca.uncertainty.observed.size() > 0 && !ca.uncertainty.observed(gy0, gx0)) continue;
      Eigen::Vector2d q;
      if (!cb->model.Project(b_from_a * (rays.col(k).normalized() * distance), &q)) continue;
      const double diff = (q - pixels.col(k)).norm();
      const int gx = k % ca.uncertainty.grid_x, gy = k / ca.uncertainty.grid_x;
      const double bound =
          ca.uncertainty.worst_sigma_px(gy, gx) + cb->uncertainty.worst_sigma_px(gy, gx);
      sum2 += diff * diff;
      worst = std::max(worst, diff);
      within += diff <= bound;
      ++n;
    }
    if (n == 0) continue;
    const double rms = std::sqrt(sum2 / n);
    double sigma_sum = 0, predicted2 = 0;
    for (int k = 0; k < pixels.cols(); ++k) {
      const int gx = k % ca.uncertainty.grid_x, gy = k / ca.uncertainty.grid_x;
      if (ca.uncertainty.observed.size() > 0 && !ca.uncertainty.observed(gy, gx)) continue;
      const double sa = ca.uncertainty.worst_sigma_px(gy, gx);
      const double sb = cb->uncertainty.worst_sigma_px(gy, gx);
      sigma_sum += (sa + sb) / n;
      predicted2 += (sa * sa + sb * sb) / n;  // the halves are independent
    }
    const double predicted = std::sqrt(predicted2);
    const double to_predicted = predicted > 0 ? rms / predicted : 0;
    worst_ratio = std::max(worst_ratio, sigma_sum > 0 ? rms / sigma_sum : 0);
    worst_to_predicted = std::max(worst_to_predicted, to_predicted);
    result[ca.name] = {{"diff_rms_px", rms},
                       {"diff_max_px", worst},
                       {"sigma_sum_mean_px", sigma_sum},
                       {"ratio", sigma_sum > 0 ? rms / sigma_sum : 0},
                       {"predicted_sigma_px", predicted},
                       {"ratio_to_predicted", to_predicted},
                       {"within_sigma_sum_fraction", static_cast<double>(within) / n}};
  }
  return {{"cameras", result},
          {"worst_ratio", worst_ratio},
          {"worst_ratio_to_predicted", worst_to_predicted},
          {"method",
           "implied rigid transform fitted to the pixels where the board was seen, then projection "
           "differences"},
          {"halves",
           {{"a",
             {{"termination", ToString(a.termination)},
              {"rms_px", a.rms_reprojection_px},
              {"frames", a.frames}}},
            {"b",
             {{"termination", ToString(b.termination)},
              {"rms_px", b.rms_reprojection_px},
              {"frames", b.frames}}}}}};
}

}  // namespace

namespace {

// A camera's board distances, tilts and normals (one per view) and its inlier corners, summed up.
PoseSpread SpreadOf(const std::vector<double>& distances, const std::vector<double>& tilts,
                    const std::vector<Eigen::Vector3d>& normals,
                    const std::vector<Eigen::Vector2d>& observed, int width, int height) {
  PoseSpread spread;
  if (distances.empty()) return spread;
  const auto [dmin, dmax] = std::minmax_element(distances.begin(), distances.end());
  const auto [tmin, tmax] = std::minmax_element(tilts.begin(), tilts.end());
  spread.distance_min_m = *dmin;
  spread.distance_max_m = *dmax;
  spread.tilt_min_deg = *tmin;
  spread.tilt_max_deg = *tmax;
  for (size_t a = 0; a < normals.size(); ++a) {
    for (size_t b = a + 1; b < normals.size(); ++b) {
      spread.normal_spread_deg = std::max(
          spread.normal_spread_deg,
          std::acos(std::clamp(normals[a].dot(normals[b]), -1.0, 1.0)) * 180 / std::numbers::pi);
    }
  }
  constexpr int kCellsX = 8, kCellsY = 6;
  std::set<int> cells;
  for (const auto& p : observed) {
    const int x = std::clamp(static_cast<int>((p.x() + 0.5) * kCellsX / width), 0, kCellsX - 1);
    const int y = std::clamp(static_cast<int>((p.y() + 0.5) * kCellsY / height), 0, kCellsY - 1);
    cells.insert(y * kCellsX + x);
  }
  spread.coverage = static_cast<double>(cells.size()) / (kCellsX * kCellsY);
  return spread;
}

// The side, in pixels, of what a detector reads on `layout` in one view: a tag (AprilTag
// boards), an ArUco marker (ChArUco boards) or a square (chessboards), measured between
// neighbouring seen grid points along the rows and the columns (per grid step between them),
// the median over the view. NaN when no two seen points share a row or a column.
double FeatureSidePx(const BoardObservation& view, const BoardLayout& layout, int width_n,
                     int height_n) {
  std::vector<double> steps;
  const auto seen = [&](int i, int j) { return view.points(j * width_n + i, 2) > 0; };
  const auto pixel = [&](int i, int j) {
    return Eigen::Vector2d(view.points(j * width_n + i, 0), view.points(j * width_n + i, 1));
  };
  for (int j = 0; j < height_n; ++j) {
    for (int i = 0; i < width_n; ++i) {
      if (!seen(i, j)) continue;
      for (int d = 1; i + d < width_n; ++d) {
        if (!seen(i + d, j)) continue;
        steps.push_back((pixel(i + d, j) - pixel(i, j)).norm() / d);
        break;
      }
      for (int d = 1; j + d < height_n; ++d) {
        if (!seen(i, j + d)) continue;
        steps.push_back((pixel(i, j + d) - pixel(i, j)).norm() / d);
        break;
      }
    }
  }
  if (steps.empty()) return std::numeric_limits<double>::quiet_NaN();
  std::nth_element(steps.begin(), steps.begin() + static_cast<std::ptrdiff_t>(steps.size() / 2),
                   steps.end());
  const double step = steps[steps.size() / 2];
  if (layout.type == BoardType::kCharuco) return step * layout.marker_side / layout.spacing;
  return step * layout.feature_steps();
}

// What detection reads on `layout` and from how many pixels across. AprilTag boards: holocap's
// detection drops a tag whose sides are shorter than DetectionOptions::min_tag_side_px (passed on
// as CalibrationOptions::tag_read_px). ChArUco markers: OpenCV's ArUco decodes a marker from about
// one pixel per bit cell with its border (10 for 6 x 6 bits). Chessboards: OpenCV's finder drops
// quadrilaterals under 25 px² once its dilation has eaten into the black squares.
constexpr double kNearReadable = 1.5;

struct ReadableFeature {
  const char* plural;
  const char* one;
  std::string from;  // "from 12 px (...)", "from about 10 px"
  double px;
};
ReadableFeature ReadableFeatureOf(const BoardLayout& layout, const CalibrationOptions& options) {
  switch (layout.type) {
    case BoardType::kAprilGrid: {
      const double px =
          options.tag_read_px > 0 ? options.tag_read_px : DetectionOptions{}.min_tag_side_px;
      return {"tags", "a tag", Cat("from ", px, " px (min_tag_side_px)"), px};
    }
    case BoardType::kCharuco:
      return {"markers", "a marker", "from about 10 px", 10};
    case BoardType::kChessboard:
      break;
  }
  return {"squares", "a square", "from about 8 px", 8};
}

// How far apart two estimates of one camera's pose relative to another are: the angle between
// their rotations or between their baselines' directions, whichever is larger (a seed's focal
// length scales the baseline, not its direction).
double RelativePoseApartDeg(const Pose& a, const Pose& b) {
  const double rotation = RotationAngleDeg(a.linear().transpose() * b.linear());
  const Eigen::Vector3d ta = a.translation(), tb = b.translation();
  if (ta.norm() == 0 || tb.norm() == 0) return rotation;
  const double cosine = std::clamp(ta.normalized().dot(tb.normalized()), -1.0, 1.0);
  return std::max(rotation, std::acos(cosine) * 180 / std::numbers::pi);
}

// The calibration of one rig: each step a method, the state between steps in members.
class Calibrator {
 public:
  Calibrator(const BoardLayout& layout, const std::vector<CalibrationCamera>& cameras,
             const std::vector<BoardObservation>& observations, const CalibrationOptions& options,
             Report* report)
      : layout_(layout),
        board_(layout),
        cameras_(cameras),
        observations_(observations),
        options_(options),
        report_(report),
        turns_(calibration_internal::AmbiguousBoardTurns(layout)) {
    for (int turn : turns_) {
      const std::vector<int> order =
          calibration_internal::TurnedGridOrder(board_.width_n(), board_.height_n(), turn);
      const std::vector<Eigen::Vector3d> grid = board_.GridPoints();
      std::vector<Eigen::Vector3d> original;
      original.reserve(order.size());
      for (int index : order) original.push_back(grid[index]);
      orders_.push_back(order);
      board_from_turned_.push_back(calibration_internal::FitRigid(grid, original));
    }
  }

  CalibrationSummary Run();

 private:
  CalibrationSummary Solve();
  void CheckInput();
  void SelectViews();
  void SeedCamera(int c);
  void MeasureFeatures(int c);
  void FlagTooFewViews(int c, const std::string& why);
  bool PlaceCameras();
  Pose RelativePose(const std::vector<std::pair<int, int>>& pairs) const;
  void OrderViews();
  void Turn(int k, size_t turn);
  void BuildProblem();
  void NoteLensModels();
  bool SolveStereographic();
  bool SolveFinalModel();
  bool SolveCameraAlone(int m);
  void Absorb(const Problem& q, int only);
  void CollectResiduals();
  void EstimateUncertainty();
  bool CameraUncertaintyOf(int m, Factorization& joint, bool joint_ok);
  std::string UnconstrainedLens(const CalibratedCamera& out) const;
  void CrossValidation();
  std::string CrossValidationBeyondPrediction() const;
  void CheckModelFit();
  void Conclude();

  // Runs mrcal on `q`, records the stage and says how mrcal's solve ended.
  SolverEnd Stage(const std::string& name, Problem& q, bool to_report);
  CalibrationSummary End(Termination state, std::string why);
  double Elapsed() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  }

  const BoardLayout& layout_;
  const Board board_;
  const std::vector<CalibrationCamera>& cameras_;
  std::vector<BoardObservation> observations_;  // numbered alike within each frame set
  const CalibrationOptions& options_;
  Report* report_;
  // The board's ambiguous turns (calibration_internal::AmbiguousBoardTurns), each as the grid
  // order and the rigid motion from the turned board frame to the board's own.
  std::vector<int> turns_;
  std::vector<std::vector<int>> orders_;
  std::vector<Pose> board_from_turned_;
  std::chrono::steady_clock::time_point start_;

  CalibrationSummary summary_;
  std::map<std::string, int> index_of_;
  int reference_ = 0;
  std::vector<std::vector<int>> views_;  // usable observations per camera
  std::vector<double> focal_;            // stereographic seed focal per camera
  std::map<int, Pose> cam_from_board_;   // seeded board pose by observation index
  std::vector<Pose> cam_from_ref_;       // seeded rig geometry
  std::vector<bool> placed_;             // joined to the reference camera's group
  Problem p_;                            // the joint problem
  std::map<int64_t, std::vector<std::pair<int, int>>> frame_members_;  // set -> (mrcal cam, obs)
  std::vector<std::string> requested_;      // lens model asked for, per mrcal camera
  std::vector<mrcal_point3_t> given_pool_;  // the joint pool before outlier rejection
  std::vector<double> core_;                // the stereographic stages' intrinsics
  std::map<int, Problem> alone_;            // cameras re-solved alone, by mrcal camera
  std::vector<double> all_residuals_;       // every inlier residual coordinate
  std::string unconverged_;                 // stages whose cost still fell
  std::string model_mismatch_;              // why the lens model cannot describe the lenses
};

CalibrationSummary Calibrator::Run() {
  CheckInput();
  start_ = std::chrono::steady_clock::now();
  // Past the preconditions, whatever goes wrong is the solve's ending, never an exception: a
  // model with a negative focal length (corners numbered from other ends, say) or a camera
  // millions of metres away (a board layout in micrometres) is FAILURE.
  try {
    return Solve();
  } catch (const std::exception& e) {
    for (CalibratedCamera& camera : summary_.cameras) camera.solved = false;  // nothing written
    return End(Termination::kFailure,
               Cat("the solve gave no usable model: ", e.what(),
                   " (a board layout not in metres, corners numbered inconsistently between "
                   "cameras, or views that do not constrain the lens?)"));
  }
}

CalibrationSummary Calibrator::Solve() {
  SelectViews();
  focal_.assign(cameras_.size(), 0);
  for (size_t c = 0; c < cameras_.size(); ++c) SeedCamera(static_cast<int>(c));
  if (!PlaceCameras()) {
    summary_.End(Termination::kDegenerate, Cat("reference camera ", summary_.reference_camera, ": ",
                                               summary_.cameras[reference_].flag));
    return summary_;
  }
  OrderViews();
  for (const auto& views : views_) {
    for (int k : views) summary_.solved_views.push_back(observations_[k]);
  }
  BuildProblem();
  NoteLensModels();
  if (!SolveStereographic()) return summary_;
  if (!SolveFinalModel()) return summary_;
  for (int m = 0; m < p_.ncams(); ++m) {
    if (!Represents(summary_.lensmodel, requested_[m]) && !SolveCameraAlone(m)) return summary_;
  }
  summary_.solve_seconds = Elapsed();
  CollectResiduals();
  EstimateUncertainty();
  if (options_.cross_validation) CrossValidation();
  CheckModelFit();
  Conclude();
  return summary_;
}

// Broken preconditions are errors, not states.
void Calibrator::CheckInput() {
  options_.Check();
  if (cameras_.empty()) Fail("calibration needs at least one camera");
  for (size_t k = 0; k < cameras_.size(); ++k) {
    if (cameras_[k].width <= 0 || cameras_[k].height <= 0) {
      Fail("camera '", cameras_[k].name, "' has no imager size");
    }
    ParseModel(cameras_[k].lensmodel);
    if (!index_of_.emplace(cameras_[k].name, static_cast<int>(k)).second) {
      Fail("camera '", cameras_[k].name, "' is listed twice");
    }
  }
  const int points_per_view = board_.width_n() * board_.height_n();
  for (const auto& obs : observations_) {
    if (!index_of_.count(obs.sensor)) Fail("observation of unknown camera '", obs.sensor, "'");
    if (obs.points.rows() != points_per_view) {
      Fail("observation of '", obs.sensor, "' in set ", obs.frame_set, " has ", obs.points.rows(),
           " points; the board has ", points_per_view);
    }
  }
  summary_.cameras.resize(cameras_.size());
  for (size_t k = 0; k < cameras_.size(); ++k) summary_.cameras[k].name = cameras_[k].name;
  summary_.reference_camera =
      options_.reference_camera.empty() ? cameras_[0].name : options_.reference_camera;
  if (!index_of_.count(summary_.reference_camera)) {
    Fail("reference camera '", summary_.reference_camera, "' is not among the cameras");
  }
  reference_ = index_of_[summary_.reference_camera];
}

void Calibrator::SelectViews() {
  views_.assign(cameras_.size(), {});
  std::map<std::string, int> too_few;
  for (size_t k = 0; k < observations_.size(); ++k) {
    if (observations_[k].seen() >= options_.min_points_per_view) {
      views_[index_of_[observations_[k].sensor]].push_back(static_cast<int>(k));
    } else {
      ++too_few[observations_[k].sensor];
    }
  }
  if (!too_few.empty()) {
    std::string counts;
    for (const auto& [sensor, count] : too_few) {
      counts += Cat(counts.empty() ? "" : ", ", sensor, " ", count);
    }
    summary_.warnings.push_back(Cat("views with fewer than ", options_.min_points_per_view,
                                    " board points left out of the solve: ", counts));
  }
}

// A stereographic focal length for camera c and every one of its views' board poses.
void Calibrator::SeedCamera(int c) {
  auto& out = summary_.cameras[c];
  MeasureFeatures(c);
  out.views = static_cast<int>(views_[c].size());
  if (out.views < options_.min_views_per_camera) {
    FlagTooFewViews(c, Cat("only ", out.views, " usable board views (needs ",
                           options_.min_views_per_camera, ")"));
    return;
  }
  std::vector<const BoardObservation*> list;
  for (int k : views_[c]) list.push_back(&observations_[k]);
  const double cx = (cameras_[c].width - 1) / 2.0, cy = (cameras_[c].height - 1) / 2.0;
  // mrcal's seeding tries several focal scales; the stereographic focal matching a pinhole
  // seed lies below it for wide lenses.
  const double f0 = SeedFocal(list, board_, cameras_[c].width, cameras_[c].height);
  double best_error = 1e300;
  for (double scale : {1.0, 0.85, 0.7, 0.55, 0.4}) {
    double total = 0;
    int ok = 0;
    for (int k : views_[c]) {
      Pose pose;
      if (SeedView(observations_[k], board_, f0 * scale, cx, cy, &pose)) {
        total += SeedViewError(observations_[k], board_, f0 * scale, cx, cy, pose);
        ++ok;
      }
    }
    const double error =
        ok > 0 ? total / ok + 1e3 * (static_cast<int>(views_[c].size()) - ok) : 1e300;
    if (error < best_error) {
      best_error = error;
      focal_[c] = f0 * scale;
    }
  }
  std::vector<int> seeded;
  for (int k : views_[c]) {
    Pose pose;
    if (SeedView(observations_[k], board_, focal_[c], cx, cy, &pose)) {
      cam_from_board_[k] = pose;
      seeded.push_back(k);
    }
  }
  views_[c] = seeded;
  out.views = static_cast<int>(seeded.size());
  if (out.views < options_.min_views_per_camera) {
    FlagTooFewViews(c, Cat("only ", out.views, " board views could be seeded (needs ",
                           options_.min_views_per_camera, ")"));
  }
}

// The size of the board's tags (markers, squares) in every view of camera c that detection
// found, however few points it holds: the smallest and the median view.
void Calibrator::MeasureFeatures(int c) {
  std::vector<double> sides;
  for (const auto& view : observations_) {
    if (view.sensor != cameras_[c].name) continue;
    const double side = FeatureSidePx(view, layout_, board_.width_n(), board_.height_n());
    if (std::isfinite(side)) sides.push_back(side);
  }
  if (sides.empty()) return;
  std::sort(sides.begin(), sides.end());
  summary_.cameras[c].feature_side_px_min = sides.front();
  summary_.cameras[c].feature_side_px_median = sides[sides.size() / 2];
}

// Flags camera c for too few views, saying why when the views found show the board's tags
// (markers, squares) near the size detection reads them from (the median view under
// kNearReadable times it): half the views found were then within that factor of being lost, the
// views missed were likely those where the board was smaller still, and a larger board, a closer
// one or more pixels help.
void Calibrator::FlagTooFewViews(int c, const std::string& why) {
  CalibratedCamera& out = summary_.cameras[c];
  out.flag = why;
  const ReadableFeature feature = ReadableFeatureOf(layout_, options_);
  if (!(out.feature_side_px_median < kNearReadable * feature.px)) return;
  const auto rounded = [](double px) { return std::round(px * 10) / 10; };
  out.flag += Cat("; the board's ", feature.plural, " were ", rounded(out.feature_side_px_min), "-",
                  rounded(out.feature_side_px_median),
                  " px across where found (the smallest and the median view), and ", feature.one,
                  " is read ", feature.from, ": print larger ", feature.plural,
                  ", bring the board closer, or capture the board at full resolution");
}

// The camera graph: cameras joined by shared frame sets, explored from the reference camera
// along the edges with the most shared views. False when the reference camera is flagged.
bool Calibrator::PlaceCameras() {
  const size_t n = cameras_.size();
  std::vector<std::map<int64_t, int>> by_set(n);
  for (size_t c = 0; c < n; ++c) {
    if (!summary_.cameras[c].flag.empty()) continue;
    for (int k : views_[c]) by_set[c][observations_[k].frame_set] = k;
  }
  auto shared = [&](int a, int b) {
    std::vector<std::pair<int, int>> pairs;
    for (const auto& [set, ka] : by_set[a]) {
      auto it = by_set[b].find(set);
      if (it != by_set[b].end()) pairs.emplace_back(ka, it->second);
    }
    return pairs;
  };
  if (!summary_.cameras[reference_].flag.empty()) return false;
  cam_from_ref_.assign(n, Pose::Identity());
  placed_.assign(n, false);
  placed_[reference_] = true;
  for (;;) {
    int best_from = -1, best_to = -1;
    size_t best_count = 0;
    for (size_t a = 0; a < n; ++a) {
      if (!placed_[a]) continue;
      for (size_t b = 0; b < n; ++b) {
        if (placed_[b] || !summary_.cameras[b].flag.empty()) continue;
        const size_t count = shared(static_cast<int>(a), static_cast<int>(b)).size();
        if (count > best_count) {
          best_count = count;
          best_from = static_cast<int>(a);
          best_to = static_cast<int>(b);
        }
      }
    }
    if (best_to < 0) break;
    cam_from_ref_[best_to] = RelativePose(shared(best_from, best_to)) * cam_from_ref_[best_from];
    placed_[best_to] = true;
  }
  for (size_t c = 0; c < n; ++c) {
    if (!placed_[c] && summary_.cameras[c].flag.empty()) {
      summary_.cameras[c].flag = "never shares a board view with the reference camera's group";
    }
  }
  return true;
}

// b_from_a of two cameras from the views they share (pairs of observation indices, a's first).
// A symmetric board may be numbered from other ends in the two views of one pair: each pair
// offers one estimate per turn of the board, and the estimate the other pairs lie closest to
// under their best turns wins (ties: the one most pairs give unturned, OpenCV's numbering);
// the pairs within max_order_disagreement_deg of it are averaged. An estimate differs from
// another by the angle between their rotations or between their baselines' directions, which
// the seeds' focal lengths do not scale. A wrong turn moves camera b around the board's normal:
// its estimates scatter from pair to pair as the board moves, while the right ones stay within
// the seeds' errors (a few degrees).
Pose Calibrator::RelativePose(const std::vector<std::pair<int, int>>& pairs) const {
  auto estimate = [&](const std::pair<int, int>& pair, size_t t) {
    return cam_from_board_.at(pair.second) * board_from_turned_[t] *
           cam_from_board_.at(pair.first).inverse();
  };
  const double tolerance = options_.max_order_disagreement_deg;
  Pose best = estimate(pairs.front(), 0);
  double best_cost = std::numeric_limits<double>::infinity();
  int best_unturned = -1;
  for (const auto& candidate_pair : pairs) {
    for (size_t t = 0; t < turns_.size(); ++t) {
      const Pose candidate = estimate(candidate_pair, t);
      double cost = 0;
      int unturned = 0;
      for (const auto& pair : pairs) {
        double closest = tolerance;
        size_t closest_turn = turns_.size();
        for (size_t u = 0; u < turns_.size(); ++u) {
          const double apart = RelativePoseApartDeg(candidate, estimate(pair, u));
          if (apart < closest) {
            closest = apart;
            closest_turn = u;
          }
        }
        cost += closest;
        unturned += closest_turn == 0;
      }
      if (cost < best_cost - 1e-9 || (cost <= best_cost + 1e-9 && unturned > best_unturned)) {
        best = candidate;
        best_cost = cost;
        best_unturned = unturned;
      }
    }
  }
  std::vector<Pose> agreeing;
  for (const auto& pair : pairs) {
    double closest = tolerance;
    std::optional<Pose> nearest;
    for (size_t u = 0; u < turns_.size(); ++u) {
      const Pose e = estimate(pair, u);
      if (const double apart = RelativePoseApartDeg(best, e); apart <= closest) {
        closest = apart;
        nearest = e;
      }
    }
    if (nearest) agreeing.push_back(*nearest);
  }
  return agreeing.empty() ? best : AveragePoses(agreeing);
}

// Observation k numbered after the board's turn `turn` (an index into turns_), its seeded pose
// with it.
void Calibrator::Turn(int k, size_t turn) {
  BoardObservation& obs = observations_[k];
  const auto original = obs.points;
  for (size_t r = 0; r < orders_[turn].size(); ++r) {
    obs.points.row(static_cast<Eigen::Index>(r)) = original.row(orders_[turn][r]);
  }
  cam_from_board_[k] = cam_from_board_[k] * board_from_turned_[turn];
}

// Symmetric boards: within each frame set, every placed camera's view numbered as the view
// of the camera with the most views (the anchor). Each view takes the turn that brings its
// pose relative to the anchor's camera closest to the two cameras' relative pose: from the
// views they share (RelativePose) when they share two or more, else from the placed rig. A
// view farther than max_order_disagreement_deg from it under every turn is left out.
void Calibrator::OrderViews() {
  if (turns_.size() < 2) return;
  std::map<int64_t, std::vector<std::pair<int, int>>> by_set;  // set -> (camera, observation)
  std::vector<std::map<int64_t, int>> view_in_set(cameras_.size());
  for (size_t c = 0; c < cameras_.size(); ++c) {
    if (!placed_[c] || !summary_.cameras[c].flag.empty()) continue;
    for (int k : views_[c]) {
      by_set[observations_[k].frame_set].emplace_back(static_cast<int>(c), k);
      view_in_set[c][observations_[k].frame_set] = k;
    }
  }
  std::map<std::pair<int, int>, Pose> relative;  // (a, b) -> b_from_a
  auto relative_pose = [&](int a, int b) {
    auto it = relative.find({a, b});
    if (it != relative.end()) return it->second;
    std::vector<std::pair<int, int>> pairs;
    for (const auto& [set, ka] : view_in_set[a]) {
      if (auto kb = view_in_set[b].find(set); kb != view_in_set[b].end())
        pairs.emplace_back(ka, kb->second);
    }
    Pose pose =
        pairs.size() >= 2 ? RelativePose(pairs) : cam_from_ref_[b] * cam_from_ref_[a].inverse();
    relative.emplace(std::make_pair(a, b), pose);
    return pose;
  };
  const double tolerance = options_.max_order_disagreement_deg;
  std::set<int> dropped;
  for (const auto& [set, members] : by_set) {
    if (members.size() < 2) continue;
    const auto anchor = *std::max_element(members.begin(), members.end(), [&](auto x, auto y) {
      return views_[x.first].size() < views_[y.first].size();
    });
    for (const auto& [c, k] : members) {
      if (k == anchor.second) continue;
      const Pose expected = relative_pose(anchor.first, c);
      size_t chosen = 0;
      double closest = std::numeric_limits<double>::infinity();
      for (size_t t = 0; t < turns_.size(); ++t) {
        const Pose seen = cam_from_board_.at(k) * board_from_turned_[t] *
                          cam_from_board_.at(anchor.second).inverse();
        const double apart = RelativePoseApartDeg(expected, seen);
        if (apart < closest) {
          closest = apart;
          chosen = t;
        }
      }
      if (!(closest <= tolerance)) {
        dropped.insert(k);
        summary_.dropped_views.push_back(
            {cameras_[c].name, set,
             Cat("no numbering of the board agrees with ", cameras_[anchor.first].name,
                 "'s view of the frame set: the closest (", 90 * turns_[chosen],
                 " degrees turned) is ", std::round(closest * 10) / 10, " degrees off (limit ",
                 tolerance, ")")});
      } else if (chosen != 0) {
        Turn(k, chosen);
        ++summary_.reordered_views;
      }
    }
  }
  if (dropped.empty()) return;
  for (size_t c = 0; c < cameras_.size(); ++c) {
    std::erase_if(views_[c], [&](int k) { return dropped.count(k) > 0; });
    CalibratedCamera& out = summary_.cameras[c];
    out.views = static_cast<int>(views_[c].size());
    if (out.flag.empty() && out.views < options_.min_views_per_camera) {
      FlagTooFewViews(static_cast<int>(c),
                      Cat("only ", out.views, " board views numbered as the other cameras' (needs ",
                          options_.min_views_per_camera, ")"));
    }
  }
}

// The mrcal problem: the reference camera first (mrcal's reference frame), then the rest.
void Calibrator::BuildProblem() {
  p_.layout = layout_;
  p_.width_n = board_.width_n();
  p_.height_n = board_.height_n();
  p_.camera_index.push_back(reference_);
  for (size_t c = 0; c < cameras_.size(); ++c) {
    if (static_cast<int>(c) != reference_ && placed_[c])
      p_.camera_index.push_back(static_cast<int>(c));
  }
  for (int m = 0; m < p_.ncams(); ++m) {
    for (int k : views_[p_.camera_index[m]]) {
      frame_members_[observations_[k].frame_set].emplace_back(m, k);
    }
  }
  for (int m = 0; m < p_.ncams(); ++m) {
    const CalibrationCamera& cam = cameras_[p_.camera_index[m]];
    p_.imagersizes.push_back(cam.width);
    p_.imagersizes.push_back(cam.height);
    requested_.push_back(cam.lensmodel);
    if (m > 0) p_.extrinsics.push_back(ToMrcal(cam_from_ref_[p_.camera_index[m]]));
    p_.extrinsics_of.push_back(m - 1);
  }
  for (const auto& [set, members] : frame_members_) {
    std::vector<Pose> estimates;
    for (const auto& [m, k] : members) {
      estimates.push_back(cam_from_ref_[p_.camera_index[m]].inverse() * cam_from_board_[k]);
    }
    const int iframe = static_cast<int>(p_.frames.size());
    p_.frames.push_back(ToMrcal(AveragePoses(estimates)));
    p_.frame_sets.push_back(set);
    for (const auto& [m, k] : members) {
      mrcal_observation_board_t o;
      o.icam.intrinsics = m;
      o.icam.extrinsics = m - 1;
      o.iframe = iframe;
      p_.observations.push_back(o);
      p_.observation_source.push_back(k);
      const auto& pts = observations_[k].points;
      for (int r = 0; r < pts.rows(); ++r) {
        p_.pool.push_back(mrcal_point3_t{{pts(r, 0), pts(r, 1), pts(r, 2) > 0 ? pts(r, 2) : -1.0}});
      }
    }
  }
  given_pool_ = p_.pool;
  summary_.frames = static_cast<int>(p_.frames.size());
  summary_.observations = static_cast<int>(p_.observations.size());
  summary_.lensmodel = JointModel(requested_);
}

void Calibrator::NoteLensModels() {
  const std::set<std::string> distinct(requested_.begin(), requested_.end());
  if (distinct.size() > 1) {
    std::string alone;
    for (int m = 0; m < p_.ncams(); ++m) {
      if (!Represents(summary_.lensmodel, requested_[m])) {
        alone += (alone.empty() ? "" : ", ") + cameras_[p_.camera_index[m]].name + " (" +
                 requested_[m] + ")";
      }
    }
    summary_.notes.push_back(Cat(
        "cameras ask for ", distinct.size(), " lens models and mrcal 2.2 solves one per problem: ",
        "the rig is solved in ", summary_.lensmodel,
        alone.empty()
            ? std::string(", which contains every model asked for")
            : ", then re-solved alone in their own models against the rig's board poses: " +
                  alone));
  }
  for (const auto& c : summary_.cameras) {
    if (!c.flag.empty()) summary_.warnings.push_back(c.name + ": " + c.flag);
  }
}

SolverEnd Calibrator::Stage(const std::string& name, Problem& q, bool to_report) {
  const mrcal_stats_t stats = q.Optimize(options_.verbose);
  const SolverEnd end = JudgeEnd(q, stats);
  summary_.stages.push_back({name, q.lensmodel, stats.rms_reproj_error__pixels, stats.Noutliers,
                             Elapsed(), end.termination, end.cost, end.expected_decrease});
  if (to_report && report_ != nullptr) {
    report_->AddPoint("rms_reprojection_px", stats.rms_reproj_error__pixels,
                      static_cast<int64_t>(summary_.stages.size()));
  }
  if (end.termination == Termination::kNoConvergence) {
    unconverged_ += (unconverged_.empty() ? "" : ", ") + name;
  }
  return end;
}

CalibrationSummary Calibrator::End(Termination state, std::string why) {
  summary_.End(state, std::move(why));
  summary_.solve_seconds = Elapsed();
  return summary_;
}

// Stages 1 and 2: geometry, then the core, through a stereographic lens (as mrcal's tool).
bool Calibrator::SolveStereographic() {
  p_.SetModel("LENSMODEL_STEREOGRAPHIC");
  for (int m = 0; m < p_.ncams(); ++m) {
    const CalibrationCamera& cam = cameras_[p_.camera_index[m]];
    const double f = focal_[p_.camera_index[m]];
    for (double v : {f, f, (cam.width - 1) / 2.0, (cam.height - 1) / 2.0})
      p_.intrinsics.push_back(v);
  }
  p_.selections = Selections(false, false, false, false, false);
  if (!Stage("geometry", p_, true).IsUsable()) {
    End(Termination::kFailure, "the geometry stage produced NaN");
    return false;
  }
  p_.selections = Selections(true, false, false, false, false);
  if (!Stage("core", p_, true).IsUsable()) {
    End(Termination::kFailure, "the intrinsics-core stage produced NaN");
    return false;
  }
  if (summary_.stages.back().rms_px > options_.max_seed_rms_px) {
    End(Termination::kFailure,
        Cat("the seed does not fit the observations (", summary_.stages.back().rms_px,
            " px RMS after the stereographic stages): wrong board layout or lens?"));
    return false;
  }
  core_ = p_.intrinsics;
  return true;
}

// Stage 3: the final lens model, everything, regularised, outliers rejected.
bool Calibrator::SolveFinalModel() {
  p_.SetModel(summary_.lensmodel);
  const int nparams = p_.nparams();
  p_.intrinsics.assign(static_cast<size_t>(p_.ncams()) * nparams, 0.0);
  for (int m = 0; m < p_.ncams(); ++m) {
    for (int k = 0; k < 4; ++k) p_.intrinsics[m * nparams + k] = core_[m * 4 + k];
  }
  const bool splined = IsSplined(summary_.lensmodel);
  const bool has_core = mrcal_lensmodel_metadata(&p_.parsed).has_core;
  // Splined models keep the core fixed: the spline already covers what it would do.
  p_.selections =
      Selections(has_core && !splined, nparams > 4, options_.regularization, false, false);
  if (!Stage("intrinsics", p_, true).IsUsable()) {
    End(Termination::kFailure, "the intrinsics stage produced NaN");
    return false;
  }
  p_.selections = Selections(has_core && !splined, nparams > 4, options_.regularization,
                             options_.outlier_rejection, options_.solve_board_warp);
  if (!Stage("everything", p_, true).IsUsable()) {
    End(Termination::kFailure, "the final stage produced NaN");
    return false;
  }
  if (options_.solve_board_warp) {
    summary_.board_warp_x_m = p_.warp.x2;
    summary_.board_warp_y_m = p_.warp.y2;
  }
  return true;
}

// A camera that asks for another model than the joint solve's: alone in its own model, the
// board poses held where the whole rig put them, its intrinsics (staged as above) and its pose
// relative to the reference free.
bool Calibrator::SolveCameraAlone(int m) {
  const std::string& model = requested_[m];
  Problem q = CameraAlone(p_, m, given_pool_);
  q.SetModel(model);
  const int n = q.nparams();
  q.intrinsics.assign(n, 0.0);
  for (int k = 0; k < 4; ++k) q.intrinsics[k] = core_[m * 4 + k];
  const bool q_splined = IsSplined(model);
  const bool q_core = mrcal_lensmodel_metadata(&q.parsed).has_core;
  const std::string name = cameras_[p_.camera_index[m]].name;
  {
    // Its core and pose first through a stereographic lens against the rig's board poses: the
    // joint stereographic core was fitted while the rig's other lenses pulled the board poses,
    // and a splined model's fixed core off by pixels is traded for a turned camera.
    Problem seed = q;
    seed.SetModel("LENSMODEL_STEREOGRAPHIC");
    seed.intrinsics.assign(q.intrinsics.begin(), q.intrinsics.begin() + 4);
    seed.selections = Selections(true, false, false, false, false);
    seed.selections.do_optimize_frames = false;
    seed.selections.do_optimize_extrinsics = !seed.extrinsics.empty();
    if (Stage(Cat(name, " alone, core"), seed, false).IsUsable()) {
      std::copy(seed.intrinsics.begin(), seed.intrinsics.end(), q.intrinsics.begin());
      q.extrinsics = seed.extrinsics;
    }
  }
  for (bool last : {false, true}) {
    q.selections = Selections(q_core && !q_splined, n > 4, options_.regularization,
                              last && options_.outlier_rejection, false);
    q.selections.do_optimize_frames = false;
    q.selections.do_optimize_extrinsics = !q.extrinsics.empty();
    if (!Stage(Cat(name, " alone, ", last ? "everything" : "intrinsics"), q, false).IsUsable()) {
      End(Termination::kFailure, Cat("re-solving ", name, " in ", model, " produced NaN"));
      return false;
    }
  }
  alone_.emplace(m, std::move(q));
  return true;
}

// Residuals, model and board distances of the cameras of `q` (only mrcal camera `only` when
// >= 0), from the problem that solved them.
void Calibrator::Absorb(const Problem& q, int only) {
  const int nobs = static_cast<int>(q.observations.size());
  const int np = q.nparams();
  std::vector<std::vector<double>> distances(q.ncams());
  std::vector<std::vector<Eigen::Vector3d>> normals(q.ncams());
  std::vector<std::vector<double>> tilts(q.ncams());
  const Eigen::Vector3d board_centre((q.width_n - 1) * q.layout.spacing / 2,
                                     (q.height_n - 1) * q.layout.spacing / 2, 0);
  for (int o = 0; o < nobs; ++o) {
    const int m = q.observations[o].icam.intrinsics;
    if (only >= 0 && m != only) continue;
    CalibratedCamera& out = summary_.cameras[q.camera_index[m]];
    const int base = mrcal_measurement_index_boards(o, nobs, 0, q.width_n, q.height_n);
    const Pose ref_from_board = FromMrcal(q.frames[q.observations[o].iframe]);
    const Pose cam_from_board = q.CamFromRef(m) * ref_from_board;
    distances[m].push_back((cam_from_board * board_centre).norm());
    const Eigen::Vector3d normal = cam_from_board.linear().col(2);
    const Eigen::Vector3d ray = (cam_from_board * board_centre).normalized();
    normals[m].push_back(normal);
    tilts[m].push_back(std::acos(std::clamp(std::abs(normal.dot(ray)), 0.0, 1.0)) * 180 /
                       std::numbers::pi);
    const auto& source = observations_[q.observation_source[o]].points;
    for (int r = 0; r < q.width_n * q.height_n; ++r) {
      const mrcal_point3_t& point = q.pool[static_cast<size_t>(o) * q.width_n * q.height_n + r];
      if (source(r, 2) <= 0) continue;
      if (point.z < 0) {
        ++out.outliers;
        continue;
      }
      out.observed.emplace_back(point.x, point.y);
      out.residuals.emplace_back(-q.x[base + 2 * r] / point.z, -q.x[base + 2 * r + 1] / point.z);
      ++out.points;
    }
  }
  for (int m = 0; m < q.ncams(); ++m) {
    if (only >= 0 && m != only) continue;
    CalibratedCamera& out = summary_.cameras[q.camera_index[m]];
    double s2 = 0;
    for (const auto& r : out.residuals) s2 += r.squaredNorm();
    out.rms_px = out.points > 0 ? std::sqrt(s2 / (2.0 * out.points)) : 0;
    auto& d = distances[m];
    std::nth_element(d.begin(), d.begin() + d.size() / 2, d.end());
    out.median_board_distance_m = d.empty() ? 0 : d[d.size() / 2];
    const int width = q.imagersizes[2 * static_cast<size_t>(m)];
    const int height = q.imagersizes[2 * static_cast<size_t>(m) + 1];
    out.pose_spread = SpreadOf(d, tilts[m], normals[m], out.observed, width, height);
    std::vector<double> intrinsics(q.intrinsics.begin() + static_cast<ptrdiff_t>(m) * np,
                                   q.intrinsics.begin() + static_cast<ptrdiff_t>(m + 1) * np);
    out.model = CameraModel(q.lensmodel, intrinsics, width, height, q.CamFromRef(m));
    out.solved = true;
  }
}

void Calibrator::CollectResiduals() {
  for (int m = 0; m < p_.ncams(); ++m) {
    if (!alone_.count(m)) Absorb(p_, m);
  }
  for (const auto& [m, q] : alone_) Absorb(q, 0);
  double sum2 = 0;
  int inliers = 0;
  for (int m = 0; m < p_.ncams(); ++m) {
    const CalibratedCamera& out = summary_.cameras[p_.camera_index[m]];
    summary_.outliers += out.outliers;
    inliers += out.points;
    for (const auto& r : out.residuals) {
      sum2 += r.squaredNorm();
      all_residuals_.push_back(r.x());
      all_residuals_.push_back(r.y());
    }
  }
  // Per coordinate, so it compares directly with a per-axis detection noise.
  summary_.rms_reprojection_px = inliers > 0 ? std::sqrt(sum2 / (2.0 * inliers)) : 0;
  for (size_t f = 0; f < p_.frames.size(); ++f) {
    summary_.ref_from_board[p_.frame_sets[f]] = FromMrcal(p_.frames[f]);
  }
  if (summary_.observations > 0 && summary_.outliers > 0.25 * inliers) {
    summary_.warnings.push_back(Cat(summary_.outliers, " outliers against ", inliers, " inliers"));
  }
  double mean = 0;
  for (double v : all_residuals_) mean += v / all_residuals_.size();
  double var = 0;
  for (double v : all_residuals_) var += (v - mean) * (v - mean) / all_residuals_.size();
  summary_.observed_pixel_sigma =
      options_.observed_pixel_sigma > 0 ? options_.observed_pixel_sigma : std::sqrt(var);
}

void Calibrator::EstimateUncertainty() {
  const auto u_start = std::chrono::steady_clock::now();
  Factorization joint;
  const bool joint_ok = Factor(p_, &joint);
  bool all_ok = joint_ok;
  for (int m = 0; m < p_.ncams(); ++m) all_ok = CameraUncertaintyOf(m, joint, joint_ok) && all_ok;
  summary_.uncertainty_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - u_start).count();
  if (!all_ok)
    summary_.warnings.push_back("the Jacobian could not be factored: the problem is singular");
}

// Mrcal camera m's projection uncertainty and parameter sigmas; flags it ill-conditioned where
// the board was seen and the 1-sigma passes the limit. False when its problem could not be
// factored.
bool Calibrator::CameraUncertaintyOf(int m, Factorization& joint, bool joint_ok) {
  CalibratedCamera& out = summary_.cameras[p_.camera_index[m]];
  const double distance = options_.uncertainty_distance_m > 0 ? options_.uncertainty_distance_m
                                                              : out.median_board_distance_m;
  const double sigma = summary_.observed_pixel_sigma;
  // A camera re-solved alone: its noise propagated as in a single-camera calibration.
  Factorization own;
  auto it = alone_.find(m);
  Problem mono;
  if (it != alone_.end()) mono = CameraFrame(it->second);
  const bool ok = it == alone_.end() ? joint_ok : Factor(mono, &own);
  if (ok) {
    Problem& q = it == alone_.end() ? p_ : mono;
    Factorization& f = it == alone_.end() ? joint : own;
    const int icam = it == alone_.end() ? m : 0;
    if (options_.uncertainty) {
      out.uncertainty = Uncertainty(q, f, icam, distance, sigma, options_.uncertainty_grid_x,
                                    options_.uncertainty_grid_y);
    }
    ParameterSigma(q, f, icam, sigma, &out);
  } else {
    out.uncertainty.worst_px = out.uncertainty.mean_px = std::numeric_limits<double>::infinity();
    out.focal_sigma_views_rel = std::numeric_limits<double>::infinity();  // singular
  }
  // Where the board never was (a fisheye's corners), any model is a guess; judge the solve
  // where it has data.
  CameraUncertainty& u = out.uncertainty;
  if (ok && u.grid_x > 0) {
    const int width = out.model.width(), height = out.model.height();
    u.observed =
        Eigen::Matrix<bool, Eigen::Dynamic, Eigen::Dynamic>::Constant(u.grid_y, u.grid_x, false);
    for (const auto& q : out.observed) {
      const int gx =
          std::clamp(static_cast<int>((q.x() + 0.5) * u.grid_x / width), 0, u.grid_x - 1);
      const int gy =
          std::clamp(static_cast<int>((q.y() + 0.5) * u.grid_y / height), 0, u.grid_y - 1);
      u.observed(gy, gx) = true;
    }
    u.worst_observed_px = 0;
    for (int gy = 0; gy < u.grid_y; ++gy) {
      for (int gx = 0; gx < u.grid_x; ++gx) {
        if (!u.observed(gy, gx)) continue;
        const double s = u.worst_sigma_px(gy, gx);
        u.worst_observed_px = std::isfinite(s) ? std::max(u.worst_observed_px, s)
                                               : std::numeric_limits<double>::infinity();
      }
    }
  } else {
    u.worst_observed_px = std::numeric_limits<double>::infinity();
  }
  if (options_.uncertainty && !(u.worst_observed_px <= options_.max_uncertainty_px)) {
    out.flag = Cat("ill-conditioned: worst projection 1-sigma where the board was seen ",
                   u.worst_observed_px, " px (limit ", options_.max_uncertainty_px, ")");
  }
  if (const std::string why = UnconstrainedLens(out); !why.empty())
    out.flag += (out.flag.empty() ? "" : "; ") + why;
  return ok;
}

// Why the views leave the camera's lens unconstrained (its focal length's 1-sigma beyond
// max_focal_sigma_rel of it, or not computable), with its pose spread; empty when they do not.
std::string Calibrator::UnconstrainedLens(const CalibratedCamera& out) const {
  // NaN: no focal length in the state (a splined model's core held fixed); the projection
  // uncertainty judges those.
  const PoseSpread& s = out.pose_spread;
  if (out.views > 0 && s.normal_spread_deg < options_.min_normal_spread_deg) {
    return Cat("its ", out.views, " views show the board in one pose (normals within ",
               std::round(s.normal_spread_deg * 100) / 100, " deg, limit ",
               options_.min_normal_spread_deg, "; distance ",
               std::round(s.distance_min_m * 100) / 100, "..",
               std::round(s.distance_max_m * 100) / 100,
               " m): one plane pose does not constrain a lens, however many frames repeat it");
  }
  const double worst = out.focal_sigma_views_rel;
  if (std::isnan(worst) || worst <= options_.max_focal_sigma_rel) return "";
  return Cat("its views do not constrain its lens: focal length 1-sigma from the views alone ",
             std::round(worst * 1e4) / 100, "% of it (limit ", 100 * options_.max_focal_sigma_rel,
             "%); board tilt ", std::round(s.tilt_min_deg), "..", std::round(s.tilt_max_deg),
             " deg, normals within ", std::round(s.normal_spread_deg * 10) / 10, " deg, distance ",
             std::round(s.distance_min_m * 100) / 100, "..",
             std::round(s.distance_max_m * 100) / 100, " m, ", std::round(s.coverage * 100),
             "% of the imager covered");
}

namespace {

// The options of a solve whose result its caller judges (the cross-validation halves, the fit
// check's richer model): none of the solve's own trust checks, no nested solves.
CalibrationOptions OptionsJudgedByTheCaller(const CalibrationOptions& options) {
  CalibrationOptions judged = options;
  judged.cross_validation = false;
  judged.check_model_fit = false;
  judged.max_uncertainty_px = 1e9;
  judged.max_focal_sigma_rel = 1e9;
  judged.min_normal_spread_deg = 0;
  return judged;
}

}  // namespace

// Two disjoint halves of the frame sets solved alone and compared.
void Calibrator::CrossValidation() {
  // A seeded shuffle, not odd/even: sequences often alternate their poses.
  std::vector<size_t> order(p_.frame_sets.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::shuffle(order.begin(), order.end(), std::mt19937_64(1));
  std::vector<BoardObservation> half[2];
  for (size_t i = 0; i < order.size(); ++i) {
    for (const auto& [m, k] : frame_members_[p_.frame_sets[order[i]]]) {
      half[2 * i < order.size() ? 0 : 1].push_back(observations_[k]);
    }
  }
  // Judged here against each other instead.
  CalibrationOptions half_options = OptionsJudgedByTheCaller(options_);
  half_options.min_views_per_camera = std::max(3, options_.min_views_per_camera / 2);
  const CalibrationSummary a = Calibrator(layout_, cameras_, half[0], half_options, nullptr).Run();
  const CalibrationSummary b = Calibrator(layout_, cameras_, half[1], half_options, nullptr).Run();
  summary_.cross_validation = CrossValidate(a, b);
}

namespace {

// The model the fit check solves again in: mrcal's richest OpenCV model, a rational radial
// term over the tangential ones.
constexpr const char* kRicherLensModel = "LENSMODEL_OPENCV8";

int LensModelParameters(const std::string& name) {
  mrcal_lensmodel_t parsed;
  if (!mrcal_lensmodel_from_name(&parsed, name.c_str())) return 0;
  return mrcal_lensmodel_num_params(&parsed);
}

// The share of n squared standard normal values' mean that chance exceeds with probability
// 1e-6: chi2_{1-1e-6}(n) / n by Wilson and Hilferty's cube-root approximation.
double ChiSquareMeanBound(int n) {
  constexpr double kZ = 4.753;  // the standard normal's 1 - 1e-6 quantile
  const double a = 2.0 / (9.0 * n);
  return std::pow(1 - a + kZ * std::sqrt(a), 3);
}

}  // namespace

// Each camera's residuals against the noise expected of its corners: a lens model that cannot
// describe the lens leaves them far above it (mrcal's practice: residuals that look like the
// noise, not above it and not structured).
void Calibrator::CheckModelFit() {
  if (!options_.check_model_fit) return;
  nlohmann::json& fit = summary_.model_fit;
  std::map<std::string, double> noise;  // per camera name
  if (options_.observed_pixel_sigma > 0) {
    fit["noise_from"] = "observed_pixel_sigma";
    for (const auto& c : summary_.cameras) noise[c.name] = options_.observed_pixel_sigma;
  } else {
    std::vector<CalibrationCamera> richer = cameras_;
    const int richer_parameters = LensModelParameters(kRicherLensModel);
    bool any = false;
    for (CalibrationCamera& c : richer) {
      const int own = LensModelParameters(c.lensmodel);
      if (own < richer_parameters && c.lensmodel.rfind("LENSMODEL_SPLINED", 0) != 0) {
        c.lensmodel = kRicherLensModel;
        any = true;
      }
    }
    if (!any) {
      fit["checked"] = false;
      fit["why"] = Cat("no camera's model is poorer than ", kRicherLensModel,
                       " (and observed_pixel_sigma is not given)");
      return;
    }
    CalibrationOptions richer_options = OptionsJudgedByTheCaller(options_);
    richer_options.uncertainty = false;
    const CalibrationSummary solved =
        Calibrator(layout_, richer, observations_, richer_options, nullptr).Run();
    if (!IsUsable(solved.termination)) {
      fit["checked"] = false;
      fit["why"] = Cat("the ", kRicherLensModel, " solve ended ", ToString(solved.termination),
                       ": ", solved.message);
      return;
    }
    fit["noise_from"] = Cat(kRicherLensModel, "'s residuals on the same corners");
    for (size_t k = 0; k < richer.size(); ++k) {
      const CalibratedCamera* c = solved.Find(richer[k].name);
      if (richer[k].lensmodel != cameras_[k].lensmodel && c != nullptr && c->solved &&
          c->rms_px > 0) {
        noise[richer[k].name] = c->rms_px;
      }
    }
  }
  fit["checked"] = true;
  fit["cameras"] = nlohmann::json::object();
  std::string beyond, worst_line;
  double worst_ratio = 0;
  for (const CalibratedCamera& c : summary_.cameras) {
    const auto expected = noise.find(c.name);
    if (!c.solved || c.points == 0 || expected == noise.end()) continue;
    double worst_px = 0;
    for (const auto& r : c.residuals)
      worst_px = std::max({worst_px, std::abs(r.x()), std::abs(r.y())});
    const double bound = std::sqrt(ChiSquareMeanBound(2 * c.points));
    const double limit = std::max(options_.max_residual_to_noise, bound);
    const double ratio = c.rms_px / expected->second;
    fit["cameras"][c.name] = {{"rms_px", c.rms_px},
                              {"worst_px", worst_px},
                              {"noise_px", expected->second},
                              {"ratio", ratio},
                              {"chi_square_bound", bound},
                              {"limit", limit},
                              {"lensmodel", c.model.lensmodel()}};
    if (ratio <= limit) continue;
    beyond += Cat(beyond.empty() ? "" : ", ", c.name);
    if (ratio > worst_ratio) {
      worst_ratio = ratio;
      worst_line = Cat(c.model.lensmodel(), " cannot describe the lens of ", c.name, ": residuals ",
                       c.rms_px, " px RMS (worst ", worst_px,
                       " px) against the expected corner noise ", expected->second, " px (",
                       fit["noise_from"].get<std::string>(), "), ", std::round(ratio * 10) / 10,
                       "x where ", std::round(limit * 100) / 100, "x is the limit");
    }
  }
  if (!beyond.empty()) {
    model_mismatch_ = Cat(worst_line, "; cameras beyond the limit: ", beyond,
                          ": use a richer lens model (--lens-model ", kRicherLensModel,
                          ", or a splined one for a wide lens)");
  }
}

// The cameras whose cross-validation halves differ by more than max_cross_validation_ratio
// times their predicted sigma ("cam1 (2.8x the predicted 0.05 px)"), or empty.
std::string Calibrator::CrossValidationBeyondPrediction() const {
  if (!summary_.cross_validation.is_object() || !summary_.cross_validation.contains("cameras"))
    return "";
  std::string beyond;
  for (const auto& [name, camera] : summary_.cross_validation["cameras"].items()) {
    const double ratio = camera.value("ratio_to_predicted", 0.0);
    if (ratio <= options_.max_cross_validation_ratio) continue;
    beyond += Cat(beyond.empty() ? "" : ", ", name, " (", std::round(ratio * 10) / 10,
                  "x the predicted ", camera.value("predicted_sigma_px", 0.0), " px, limit ",
                  options_.max_cross_validation_ratio, "x)");
  }
  return beyond;
}

// The trust checks: a flagged camera (too few views, unconnected, ill-conditioned) makes the
// result degenerate; otherwise mrcal's own ending decides between convergence and a budget
// spent while the cost still fell.
void Calibrator::Conclude() {
  std::vector<std::string> flagged;
  for (const auto& c : summary_.cameras) {
    if (!c.flag.empty()) flagged.push_back(c.name + " (" + c.flag + ")");
  }
  const std::string solved = Cat(cameras_.size(), " cameras, ", summary_.frames, " board poses, ",
                                 summary_.observations, " views: ", summary_.rms_reprojection_px,
                                 " px RMS per coordinate, ", summary_.outliers, " outliers");
  if (!flagged.empty()) {
    std::string list;
    for (const auto& f : flagged) list += (list.empty() ? "" : "; ") + f;
    summary_.End(Termination::kDegenerate, Cat(flagged.size(), " of ", cameras_.size(),
                                               " cameras cannot be trusted: ", list));
  } else if (const std::string beyond = CrossValidationBeyondPrediction(); !beyond.empty()) {
    summary_.End(Termination::kDegenerate,
                 Cat(solved,
                     "; cross-validation: the halves differ beyond what the uncertainty "
                     "predicts in ",
                     beyond,
                     ": the uncertainty understates the error (an unmodelled lens, a camera that "
                     "moved, a bending board, or noise above the one assumed)"));
  } else if (!model_mismatch_.empty()) {
    summary_.End(Termination::kDegenerate, Cat(solved, "; ", model_mismatch_));
  } else if (!unconverged_.empty()) {
    summary_.End(Termination::kNoConvergence,
                 Cat(solved, "; mrcal stopped while the cost still fell in: ", unconverged_));
  } else {
    summary_.End(Termination::kConvergence, solved);
  }
}

}  // namespace

CalibrationSummary Calibrate(const BoardLayout& layout,
                             const std::vector<CalibrationCamera>& cameras,
                             const std::vector<BoardObservation>& observations,
                             const CalibrationOptions& options, Report* report) {
  return Calibrator(layout, cameras, observations, options, report).Run();
}

}  // namespace holocap
