// Normal equations of one Gauss-Newton step of direct alignment (gausem_core/slam/direct_alignment.py) in one pass:
// per model point, move it by the motion, project it into the observed frame, sample the observed channels and their
// gradients bilinearly, form the residuals and IRLS weights of every channel, and accumulate H = sum w J J^T,
// g = sum w J r and the truncated L1 cost, in double. Points go through in blocks of kLanes, each stage a loop over
// the block that the compiler vectorises (AVX2 where the CPU has it), the sums kept per lane until the end.
//
// Every channel's Jacobian is J_c = a_c^T B with a_c = (du_c, dv_c, -[c is depth]) its image gradients and B (3 x 6)
// the derivatives of (u, v, z) by the twist, so a point adds B^T (sum_c w_c a_c a_c^T) B to H: the channels meet in
// a 3 x 3 moment matrix first.
#include "kernels.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <memory>
#include <vector>

namespace {

struct Sums {
  std::array<double, 36> h{};
  std::array<double, 6> g{};
  double cost = 0.0;
  int64_t valid = 0;
};

struct Problem {
  const double* motion;  // (4, 4) row-major, set per step
  double fx, fy, cx, cy;
  int64_t width, height, channels, n_points;
  const double* weights;  // per channel
  double huber_delta, max_depth_residual, max_depth_slope, cap;
};

// Per-lane partial sums of a run of points, lane = point index within a block: every loop over a block's lanes is
// free of branches and cross-lane dependencies, so that the compiler vectorises it.
constexpr int64_t kLanes = 64;

struct LaneSums {
  double h[21][kLanes] = {};  // upper triangle of H, row by row
  double g[6][kLanes] = {};
  double cost[kLanes] = {};
  int64_t valid = 0;
};

template <typename scalar_t>
#if defined(__x86_64__) && defined(__linux__) && defined(__GNUC__)  // AVX2 + FMA where the CPU has them (ifunc)
__attribute__((target_clones("arch=x86-64-v3", "default")))
#endif
void add_block(const Problem& pb, const scalar_t* pts, const scalar_t* ref, int64_t first, int64_t count,
               const scalar_t* samples, double* values, LaneSums& s) {
  const double* m = pb.motion;
  const int64_t channels = pb.channels, stride = 3 * channels, row = pb.width * stride;
  const double fx = pb.fx, fy = pb.fy;
  double x[kLanes], y[kLanes], z[kLanes], u[kLanes], v[kLanes], ok[kLanes];
  for (int64_t i = 0; i < count; ++i) {
    const scalar_t* pt = pts + 3 * (first + i);
    const double px = pt[0], py = pt[1], pz = pt[2];
    x[i] = m[0] * px + m[1] * py + m[2] * pz + m[3];
    y[i] = m[4] * px + m[5] * py + m[6] * pz + m[7];
    z[i] = m[8] * px + m[9] * py + m[10] * pz + m[11];
    u[i] = fx * x[i] / z[i] + pb.cx, v[i] = fy * y[i] / z[i] + pb.cy;
    ok[i] = (z[i] > 1e-3) & (u[i] > 0.5) & (u[i] < pb.width - 0.5) & (v[i] > 0.5) & (v[i] < pb.height - 0.5);
    z[i] = ok[i] != 0.0 ? z[i] : 1.0;  // finite sums: a lane outside gets no weight and costs the cap
  }
  // bilinear samples at pixel centres (+0.5), as grid_sample with align_corners=False, all four corners inside;
  // values[c * kLanes + i]: channel c of lane i (zero outside)
  for (int64_t i = 0; i < count; ++i) {
    if (ok[i] == 0.0) {
      for (int64_t c = 0; c < stride; ++c) values[c * kLanes + i] = 0.0;
      continue;
    }
    const double ix = u[i] - 0.5, iy = v[i] - 0.5;
    const int64_t x0 = std::min<int64_t>(static_cast<int64_t>(ix), pb.width - 2);
    const int64_t y0 = std::min<int64_t>(static_cast<int64_t>(iy), pb.height - 2);
    const double wx = ix - x0, wy = iy - y0;
    const double w00 = (1 - wx) * (1 - wy), w01 = wx * (1 - wy), w10 = (1 - wx) * wy, w11 = wx * wy;
    const scalar_t* p00 = samples + (y0 * pb.width + x0) * stride;  // the four corners' 3C values lie contiguously
    const scalar_t* p01 = p00 + stride;
    for (int64_t c = 0; c < stride; ++c) {
      values[c * kLanes + i] = w00 * p00[c] + w01 * p01[c] + w10 * p00[row + c] + w11 * p01[row + c];
    }
  }
  double muu[kLanes], muv[kLanes], mvv[kLanes], muz[kLanes], mvz[kLanes], mzz[kLanes];
  double bu[kLanes], bv[kLanes], bz[kLanes], cost[kLanes], valid[kLanes];
  const double* depth = values + 6 * kLanes;
  for (int64_t i = 0; i < count; ++i) {
    const double depth_res = depth[i] - z[i];
    valid[i] = ok[i] * (depth[i] > 0) * (std::abs(depth_res) < pb.max_depth_residual);
    muu[i] = muv[i] = mvv[i] = muz[i] = mvz[i] = mzz[i] = bu[i] = bv[i] = bz[i] = cost[i] = 0.0;
  }
  // the channels' weighted moments of a = (du, dv, dz) and of a r
  for (int64_t c = 0; c < channels; ++c) {
    const double* obs = values + c * kLanes;
    const double* gu = values + (channels + c) * kLanes;
    const double* gv = values + (2 * channels + c) * kLanes;
    const double chan = pb.weights[c];
    if (c == 6) {  // depth: the observed depth moves with z (a_z = -1); no weight across a discontinuity
      for (int64_t i = 0; i < count; ++i) {
        const double res = obs[i] - z[i];
        cost[i] += chan * std::abs(res);
        const bool smooth = (std::abs(gu[i]) * fx + std::abs(gv[i]) * fy) / z[i] < pb.max_depth_slope;
        const double w = smooth * valid[i] * chan / std::max(std::abs(res), pb.huber_delta);
        muu[i] += w * gu[i] * gu[i], muv[i] += w * gu[i] * gv[i], mvv[i] += w * gv[i] * gv[i];
        bu[i] += w * gu[i] * res, bv[i] += w * gv[i] * res;
        muz[i] -= w * gu[i], mvz[i] -= w * gv[i], mzz[i] += w, bz[i] -= w * res;
      }
      continue;
    }
    const scalar_t* r = ref + (c < 6 ? c : c - 1) * pb.n_points + first;
    for (int64_t i = 0; i < count; ++i) {
      const double res = obs[i] - r[i];
      cost[i] += chan * std::abs(res);
      const double w = valid[i] * chan / std::max(std::abs(res), pb.huber_delta);
      muu[i] += w * gu[i] * gu[i], muv[i] += w * gu[i] * gv[i], mvv[i] += w * gv[i] * gv[i];
      bu[i] += w * gu[i] * res, bv[i] += w * gv[i] * res;
    }
  }
  // B: rows d(u, v, z)/dxi of the point moved by a left increment exp(xi), dp/dxi = [I | -[p]x]; H += B^T M B,
  // g += B^T (M a r), each entry a loop over the lanes
  double b[3][6][kLanes], t[3][6][kLanes], mb[3][kLanes];
  for (int64_t i = 0; i < count; ++i) {
    s.cost[i] += valid[i] * std::min(cost[i], pb.cap) + (1.0 - valid[i]) * pb.cap;
    const double inv_z = 1.0 / z[i], xn = x[i] * inv_z, yn = y[i] * inv_z;
    b[0][0][i] = fx * inv_z, b[0][1][i] = 0.0, b[0][2][i] = -fx * xn * inv_z;
    b[0][3][i] = -fx * xn * yn, b[0][4][i] = fx * (1 + xn * xn), b[0][5][i] = -fx * yn;
    b[1][0][i] = 0.0, b[1][1][i] = fy * inv_z, b[1][2][i] = -fy * yn * inv_z;
    b[1][3][i] = -fy * (1 + yn * yn), b[1][4][i] = fy * xn * yn, b[1][5][i] = fy * xn;
    b[2][0][i] = 0.0, b[2][1][i] = 0.0, b[2][2][i] = 1.0, b[2][3][i] = y[i], b[2][4][i] = -x[i], b[2][5][i] = 0.0;
  }
  const double* mm[3][3] = {{muu, muv, muz}, {muv, mvv, mvz}, {muz, mvz, mzz}};
  for (int p = 0; p < 3; ++p) {
    for (int j = 0; j < 6; ++j) {
      for (int64_t i = 0; i < count; ++i) {
        t[p][j][i] = mm[p][0][i] * b[0][j][i] + mm[p][1][i] * b[1][j][i] + mm[p][2][i] * b[2][j][i];
      }
    }
  }
  int k = 0;
  for (int a = 0; a < 6; ++a) {
    for (int j = a; j < 6; ++j, ++k) {
      for (int64_t i = 0; i < count; ++i) {
        s.h[k][i] += b[0][a][i] * t[0][j][i] + b[1][a][i] * t[1][j][i] + b[2][a][i] * t[2][j][i];
      }
    }
    for (int64_t i = 0; i < count; ++i) s.g[a][i] += b[0][a][i] * bu[i] + b[1][a][i] * bv[i] + b[2][a][i] * bz[i];
  }
  for (int64_t i = 0; i < count; ++i) s.valid += static_cast<int64_t>(valid[i]);
}

// The problem's sums over all points (H complete, both triangles), the points split among torch's threads.
Sums sum_points(const Problem& pb, const torch::Tensor& points, const torch::Tensor& ref,
                const torch::Tensor& samples) {
  std::vector<Sums> sums(at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(samples.scalar_type(), "alignment_sums", [&] {
    const auto* pts = points.data_ptr<scalar_t>();
    const auto* rf = ref.data_ptr<scalar_t>();
    const auto* smp = samples.data_ptr<scalar_t>();
    at::parallel_for(0, pb.n_points, 1024, [&](int64_t begin, int64_t end) {
      auto lanes = std::make_unique<LaneSums>();
      std::vector<double> values(3 * pb.channels * kLanes);
      for (int64_t n = begin; n < end; n += kLanes) {
        add_block(pb, pts, rf, n, std::min(kLanes, end - n), smp, values.data(), *lanes);
      }
      Sums& s = sums[at::get_thread_num()];
      for (int64_t i = 0; i < kLanes; ++i) {
        int k = 0;
        for (int a = 0; a < 6; ++a) {
          for (int j = a; j < 6; ++j, ++k) s.h[a * 6 + j] += lanes->h[k][i];
          s.g[a] += lanes->g[a][i];
        }
        s.cost += lanes->cost[i];
      }
      s.valid += lanes->valid;
    });
  });
  Sums total;
  for (const Sums& s : sums) {
    for (int i = 0; i < 6; ++i) {
      for (int j = i; j < 6; ++j) total.h[i * 6 + j] += s.h[i * 6 + j];
      total.g[i] += s.g[i];
    }
    total.cost += s.cost;
    total.valid += s.valid;
  }
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < i; ++j) total.h[i * 6 + j] = total.h[j * 6 + i];
  }
  return total;
}

// The inputs checked and made contiguous, and the problem they pose (its motion is set per step).
Problem problem_of(torch::Tensor& points, torch::Tensor& ref, torch::Tensor& samples, const std::vector<double>& camera,
                   const std::vector<double>& channel_weights, double huber_delta, double max_depth_residual,
                   double max_depth_slope, double cap) {
  points = points.contiguous(), ref = ref.contiguous(), samples = samples.contiguous();
  const int64_t n_points = points.size(0), channels = samples.size(2) / 3;
  TORCH_CHECK(samples.dim() == 3 && samples.size(2) == 3 * channels && channels >= 7, "samples must be (H, W, 3C)");
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be (N, 3)");
  TORCH_CHECK(ref.dim() == 2 && ref.size(0) == channels - 1 && ref.size(1) == n_points, "ref must be (C - 1, N)");
  TORCH_CHECK(static_cast<int64_t>(channel_weights.size()) == channels, "one weight per channel");
  TORCH_CHECK(camera.size() == 4, "camera must be (fx, fy, cx, cy)");
  TORCH_CHECK(points.scalar_type() == samples.scalar_type() && ref.scalar_type() == samples.scalar_type(),
              "points, ref and samples must share a dtype");
  return Problem{nullptr, camera[0], camera[1], camera[2], camera[3], samples.size(1), samples.size(0), channels,
                 n_points, channel_weights.data(), huber_delta, max_depth_residual, max_depth_slope, cap};
}

torch::Tensor checked_motion(const torch::Tensor& motion) {
  auto m = motion.to(torch::kFloat64).contiguous();
  TORCH_CHECK(m.dim() == 2 && m.size(0) == 4 && m.size(1) == 4, "motion must be (4, 4)");
  return m;
}

// x solving a x = b (6 x 6, row-major; a and b are overwritten) by Gaussian elimination with partial pivoting.
void solve6(double* a, double* b, double* x) {
  for (int c = 0; c < 6; ++c) {
    int pivot = c;
    for (int r = c + 1; r < 6; ++r) {
      if (std::abs(a[r * 6 + c]) > std::abs(a[pivot * 6 + c])) pivot = r;
    }
    if (pivot != c) {
      for (int j = 0; j < 6; ++j) std::swap(a[c * 6 + j], a[pivot * 6 + j]);
      std::swap(b[c], b[pivot]);
    }
    for (int r = c + 1; r < 6; ++r) {
      const double f = a[r * 6 + c] / a[c * 6 + c];
      for (int j = c; j < 6; ++j) a[r * 6 + j] -= f * a[c * 6 + j];
      b[r] -= f * b[c];
    }
  }
  for (int r = 5; r >= 0; --r) {
    double sum = b[r];
    for (int j = r + 1; j < 6; ++j) sum -= a[r * 6 + j] * x[j];
    x[r] = sum / a[r * 6 + r];
  }
}

// exp of the twist xi = (rho, omega) as a row-major 4 x 4, with the coefficients of geometry.py's se3_exp (their
// Taylor series below an angle of 1e-4).
void se3_exp(const double* xi, double* out) {
  const double wx = xi[3], wy = xi[4], wz = xi[5], t2 = wx * wx + wy * wy + wz * wz;
  double a, b, c;
  if (t2 < 1e-8) {
    a = 1 - t2 / 6 + t2 * t2 / 120, b = 0.5 - t2 / 24 + t2 * t2 / 720, c = 1.0 / 6 - t2 / 120 + t2 * t2 / 5040;
  } else {
    const double t = std::sqrt(t2);
    a = std::sin(t) / t, b = (1 - std::cos(t)) / t2, c = (t - std::sin(t)) / (t2 * t);
  }
  const double k[9] = {0, -wz, wy, wz, 0, -wx, -wy, wx, 0};
  double kk[9];
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) kk[i * 3 + j] = k[i * 3] * k[j] + k[i * 3 + 1] * k[3 + j] + k[i * 3 + 2] * k[6 + j];
  }
  for (int i = 0; i < 3; ++i) {
    double t = 0;
    for (int j = 0; j < 3; ++j) {
      const double eye = i == j ? 1.0 : 0.0;
      out[i * 4 + j] = eye + a * k[i * 3 + j] + b * kk[i * 3 + j];
      t += (eye + b * k[i * 3 + j] + c * kk[i * 3 + j]) * xi[j];
    }
    out[i * 4 + 3] = t;
  }
  out[12] = out[13] = out[14] = 0, out[15] = 1;
}

}  // namespace

namespace gausem {

// (H (6, 6), g (6), summed truncated cost, number of valid points), in double. points (N, 3) model points, ref
// (C - 1, N) their colour, semantic and feature values, motion (4, 4), samples (H, W, 3C), channels last: the
// observed stack (colour, semantics, depth, features) and its horizontal and vertical gradients; camera (fx, fy, cx,
// cy); one weight per channel. A point without a valid observed counterpart costs cap.
std::tuple<torch::Tensor, torch::Tensor, double, int64_t> alignment_normal_equations(
    torch::Tensor points, torch::Tensor ref, torch::Tensor motion, torch::Tensor samples, std::vector<double> camera,
    std::vector<double> channel_weights, double huber_delta, double max_depth_residual, double max_depth_slope,
    double cap) {
  Problem pb = problem_of(points, ref, samples, camera, channel_weights, huber_delta, max_depth_residual,
                          max_depth_slope, cap);
  const auto m = checked_motion(motion);
  pb.motion = m.data_ptr<double>();
  const Sums s = sum_points(pb, points, ref, samples);
  auto h = torch::empty({6, 6}, torch::kFloat64), g = torch::empty({6}, torch::kFloat64);
  std::copy(s.h.begin(), s.h.end(), h.data_ptr<double>());
  std::copy(s.g.begin(), s.g.end(), g.data_ptr<double>());
  return {h, g, s.cost, s.valid};
}

// A level of Gauss-Newton steps as direct_alignment.align_level takes them (its torch loop, in double): at most
// `iterations` steps from `motion`, each solving the damped normal equations (H + damping diag(H) + 1e-9 I) xi = -g
// and moving motion to exp(xi) motion; it stops before a step with fewer than 12 valid points and after a step
// |xi| < min_step. Returns (motion (4, 4) float64, the mean cost before the last step, NaN without one).
std::tuple<torch::Tensor, double> alignment_level(
    torch::Tensor points, torch::Tensor ref, torch::Tensor motion, torch::Tensor samples, std::vector<double> camera,
    std::vector<double> channel_weights, double huber_delta, double max_depth_residual, double max_depth_slope,
    double cap, int64_t iterations, double damping, double min_step) {
  Problem pb = problem_of(points, ref, samples, camera, channel_weights, huber_delta, max_depth_residual,
                          max_depth_slope, cap);
  auto m = checked_motion(motion).clone();
  double* current = m.data_ptr<double>();
  pb.motion = current;
  double cost = std::numeric_limits<double>::quiet_NaN();
  for (int64_t step = 0; step < iterations; ++step) {
    Sums s = sum_points(pb, points, ref, samples);
    if (s.valid < 12) break;
    cost = s.cost / static_cast<double>(pb.n_points);
    for (int i = 0; i < 6; ++i) s.h[i * 6 + i] += damping * s.h[i * 6 + i] + 1e-9, s.g[i] = -s.g[i];
    double xi[6], update[16], moved[16];
    solve6(s.h.data(), s.g.data(), xi);
    se3_exp(xi, update);
    for (int i = 0; i < 4; ++i) {
      for (int j = 0; j < 4; ++j) {
        moved[i * 4 + j] = update[i * 4] * current[j] + update[i * 4 + 1] * current[4 + j] +
                           update[i * 4 + 2] * current[8 + j] + update[i * 4 + 3] * current[12 + j];
      }
    }
    std::copy(moved, moved + 16, current);
    double norm = 0;
    for (const double v : xi) norm += v * v;
    if (std::sqrt(norm) < min_step) break;
  }
  return {m, cost};
}

}  // namespace gausem
