// A native Ceres driver for BAL files: the reference for experiments/ba_bench.py.
//
// Reads a BAL problem (header "ncam npoint nobs", observations, 9 values per camera:
// angle-axis r, translation t, f, k1, k2; 3 per point), builds one autodiff residual block
// per observation (Snavely's camera: P = R(r) X + t, p = -P_xy / P_z,
// predicted = f (1 + k1 |p|^2 + k2 |p|^4) p, residual = predicted - observed), and solves it
// with Levenberg-Marquardt and DENSE_SCHUR (points eliminated first), as torchslam does.
// Prints one JSON line: initial and final cost (1/2 sum r^2), iterations, seconds.
//
// Usage: bal_ceres FILE [--threads N] [--fixed-intrinsics]
#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <vector>

namespace {

struct Reprojection {
  Reprojection(double u, double v) : u_(u), v_(v) {}

  template <typename T>
  bool operator()(const T* pose, const T* intrinsics, const T* point, T* residual) const {
    T P[3];
    ceres::AngleAxisRotatePoint(pose, point, P);
    for (int k = 0; k < 3; ++k) P[k] += pose[3 + k];
    const T px = -P[0] / P[2];
    const T py = -P[1] / P[2];
    const T r2 = px * px + py * py;
    const T rho = T(1.0) + r2 * (intrinsics[1] + intrinsics[2] * r2);
    residual[0] = intrinsics[0] * rho * px - T(u_);
    residual[1] = intrinsics[0] * rho * py - T(v_);
    return true;
  }

  double u_, v_;
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2) {
    std::fprintf(stderr, "usage: bal_ceres FILE [--threads N] [--fixed-intrinsics]\n");
    return 2;
  }
  int threads = 1;
  bool fixed = false;
  for (int i = 2; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--threads") && i + 1 < argc) threads = std::atoi(argv[++i]);
    if (!std::strcmp(argv[i], "--fixed-intrinsics")) fixed = true;
  }
  FILE* f = std::fopen(argv[1], "r");
  if (!f) {
    std::fprintf(stderr, "bal_ceres: cannot open %s\n", argv[1]);
    return 2;
  }
  int C, P, O;
  if (std::fscanf(f, "%d %d %d", &C, &P, &O) != 3) return 2;
  std::vector<int> cam(O), pt(O);
  std::vector<double> uv(2 * O), poses(6 * C), intr(3 * C), points(3 * P);
  for (int k = 0; k < O; ++k)
    if (std::fscanf(f, "%d %d %lf %lf", &cam[k], &pt[k], &uv[2 * k], &uv[2 * k + 1]) != 4)
      return 2;
  for (int c = 0; c < C; ++c) {
    for (int k = 0; k < 6; ++k)
      if (std::fscanf(f, "%lf", &poses[6 * c + k]) != 1) return 2;
    for (int k = 0; k < 3; ++k)
      if (std::fscanf(f, "%lf", &intr[3 * c + k]) != 1) return 2;
  }
  for (int k = 0; k < 3 * P; ++k)
    if (std::fscanf(f, "%lf", &points[k]) != 1) return 2;
  std::fclose(f);

  const auto start = std::chrono::steady_clock::now();
  ceres::Problem problem;
  for (int k = 0; k < O; ++k) {
    auto* cost = new ceres::AutoDiffCostFunction<Reprojection, 2, 6, 3, 3>(
        new Reprojection(uv[2 * k], uv[2 * k + 1]));
    problem.AddResidualBlock(cost, nullptr, &poses[6 * cam[k]], &intr[3 * cam[k]],
                             &points[3 * pt[k]]);
  }
  if (fixed)
    for (int c = 0; c < C; ++c) problem.SetParameterBlockConstant(&intr[3 * c]);
  auto* ordering = new ceres::ParameterBlockOrdering;
  for (int j = 0; j < P; ++j) ordering->AddElementToGroup(&points[3 * j], 0);
  for (int c = 0; c < C; ++c) {
    ordering->AddElementToGroup(&poses[6 * c], 1);
    ordering->AddElementToGroup(&intr[3 * c], 1);
  }
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::DENSE_SCHUR;
  options.linear_solver_ordering.reset(ordering);
  options.trust_region_strategy_type = ceres::LEVENBERG_MARQUARDT;
  options.num_threads = threads;
  options.max_num_iterations = 50;
  options.function_tolerance = 1e-6;
  options.gradient_tolerance = 1e-10;
  options.parameter_tolerance = 1e-8;
  options.minimizer_progress_to_stdout = std::getenv("BAL_CERES_VERBOSE") != nullptr;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf(
      "{\"initial_cost\": %.10e, \"final_cost\": %.10e, \"iterations\": %d, "
      "\"linear_solves\": %d, \"jacobian_evaluations\": %d, "
      "\"seconds\": %.6f, \"solver_seconds\": %.6f, \"termination\": \"%s\"}\n",
      summary.initial_cost, summary.final_cost,
      static_cast<int>(summary.iterations.size()) - 1, summary.num_linear_solves,
      summary.num_jacobian_evaluations, seconds, summary.total_time_in_seconds,
      ceres::TerminationTypeToString(summary.termination_type));
  return summary.IsSolutionUsable() ? 0 : 1;
}
