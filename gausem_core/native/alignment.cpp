// Normal equations of one Gauss-Newton step of direct alignment (gausem_core/slam/direct_alignment.py) in one pass:
// per model point, move it by the motion, project it into the observed frame, sample the observed channels and their
// gradients bilinearly, form the residuals and IRLS weights of every channel, and accumulate H = sum w J J^T,
// g = sum w J r and the truncated L1 cost, in double, without per-point storage.
//
// Every channel's Jacobian is J_c = a_c^T B with a_c = (du_c, dv_c, -[c is depth]) its image gradients and B (3 x 6)
// the derivatives of (u, v, z) by the twist, so a point adds B^T (sum_c w_c a_c a_c^T) B to H: the channels meet in
// a 3 x 3 moment matrix first.
#include "kernels.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <vector>

namespace {

struct Sums {
  std::array<double, 36> h{};
  std::array<double, 6> g{};
  double cost = 0.0;
  int64_t valid = 0;
};

struct Problem {
  const double* motion;  // (4, 4) row-major
  double fx, fy, cx, cy;
  int64_t width, height, channels, n_points;
  const double* weights;  // per channel
  double huber_delta, max_depth_residual, max_depth_slope, cap;
};

template <typename scalar_t>
void add_point(const Problem& pb, const scalar_t* pt, const scalar_t* ref, int64_t n, const scalar_t* samples,
               double* values, Sums& s) {
  const double* m = pb.motion;
  const double px = pt[0], py = pt[1], pz = pt[2];
  const double x = m[0] * px + m[1] * py + m[2] * pz + m[3];
  const double y = m[4] * px + m[5] * py + m[6] * pz + m[7];
  const double z = m[8] * px + m[9] * py + m[10] * pz + m[11];
  const double u = pb.fx * x / z + pb.cx, v = pb.fy * y / z + pb.cy;
  if (!(z > 1e-3 && u > 0.5 && u < pb.width - 0.5 && v > 0.5 && v < pb.height - 0.5)) {
    s.cost += pb.cap;
    return;
  }
  // bilinear weights at pixel centres (+0.5), as grid_sample with align_corners=False; all four corners inside
  const double ix = u - 0.5, iy = v - 0.5;
  const int64_t x0 = std::min<int64_t>(static_cast<int64_t>(ix), pb.width - 2);
  const int64_t y0 = std::min<int64_t>(static_cast<int64_t>(iy), pb.height - 2);
  const double wx = ix - x0, wy = iy - y0;
  const double w00 = (1 - wx) * (1 - wy), w01 = wx * (1 - wy), w10 = (1 - wx) * wy, w11 = wx * wy;
  const int64_t channels = pb.channels, stride = 3 * channels, row = pb.width * stride;
  const scalar_t* p00 = samples + (y0 * pb.width + x0) * stride;  // the four corners' 3C values lie contiguously
  const scalar_t* p01 = p00 + stride;
  for (int64_t c = 0; c < stride; ++c) {
    values[c] = w00 * p00[c] + w01 * p01[c] + w10 * p00[row + c] + w11 * p01[row + c];
  }
  auto sample = [values](int64_t c) { return values[c]; };
  const double depth = sample(6), depth_res = depth - z;
  if (!(depth > 0 && std::abs(depth_res) < pb.max_depth_residual)) {
    s.cost += pb.cap;
    return;
  }
  ++s.valid;
  // the channels' weighted moments of a = (du, dv, dz) and of a r
  double muu = 0, muv = 0, mvv = 0, muz = 0, mvz = 0, mzz = 0, bu = 0, bv = 0, bz = 0, cost = 0;
  for (int64_t c = 0; c < channels; ++c) {
    const double res = c == 6 ? depth_res : sample(c) - ref[(c < 6 ? c : c - 1) * pb.n_points + n];
    const double gu = sample(channels + c), gv = sample(2 * channels + c), chan = pb.weights[c];
    cost += chan * std::abs(res);
    double w = chan / std::max(std::abs(res), pb.huber_delta);
    if (c == 6 && !((std::abs(gu) * pb.fx + std::abs(gv) * pb.fy) / z < pb.max_depth_slope)) w = 0.0;
    muu += w * gu * gu, muv += w * gu * gv, mvv += w * gv * gv;
    bu += w * gu * res, bv += w * gv * res;
    if (c == 6) {  // the observed depth moves with z: a_z = -1
      muz -= w * gu;
      mvz -= w * gv;
      mzz += w;
      bz -= w * res;
    }
  }
  s.cost += std::min(cost, pb.cap);
  // B: rows d(u, v, z)/dxi of the point moved by a left increment exp(xi), dp/dxi = [I | -[p]x]
  const double inv_z = 1.0 / z, xn = x * inv_z, yn = y * inv_z, fx = pb.fx, fy = pb.fy;
  const double b[3][6] = {{fx * inv_z, 0.0, -fx * xn * inv_z, -fx * xn * yn, fx * (1 + xn * xn), -fx * yn},
                          {0.0, fy * inv_z, -fy * yn * inv_z, -fy * (1 + yn * yn), fy * xn * yn, fy * xn},
                          {0.0, 0.0, 1.0, y, -x, 0.0}};
  const double mm[3][3] = {{muu, muv, muz}, {muv, mvv, mvz}, {muz, mvz, mzz}};
  double t[3][6];  // M B
  for (int p = 0; p < 3; ++p) {
    for (int j = 0; j < 6; ++j) t[p][j] = mm[p][0] * b[0][j] + mm[p][1] * b[1][j] + mm[p][2] * b[2][j];
  }
  for (int i = 0; i < 6; ++i) {
    for (int j = i; j < 6; ++j) s.h[i * 6 + j] += b[0][i] * t[0][j] + b[1][i] * t[1][j] + b[2][i] * t[2][j];
    s.g[i] += b[0][i] * bu + b[1][i] * bv + b[2][i] * bz;
  }
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
  points = points.contiguous(), ref = ref.contiguous(), samples = samples.contiguous();
  const auto m = motion.to(torch::kFloat64).contiguous();
  const int64_t n_points = points.size(0), channels = samples.size(2) / 3;
  TORCH_CHECK(samples.dim() == 3 && samples.size(2) == 3 * channels && channels >= 7, "samples must be (H, W, 3C)");
  TORCH_CHECK(points.dim() == 2 && points.size(1) == 3, "points must be (N, 3)");
  TORCH_CHECK(ref.dim() == 2 && ref.size(0) == channels - 1 && ref.size(1) == n_points, "ref must be (C - 1, N)");
  TORCH_CHECK(m.dim() == 2 && m.size(0) == 4 && m.size(1) == 4, "motion must be (4, 4)");
  TORCH_CHECK(static_cast<int64_t>(channel_weights.size()) == channels, "one weight per channel");
  TORCH_CHECK(camera.size() == 4, "camera must be (fx, fy, cx, cy)");
  TORCH_CHECK(points.scalar_type() == samples.scalar_type() && ref.scalar_type() == samples.scalar_type(),
              "points, ref and samples must share a dtype");
  const Problem pb{m.data_ptr<double>(), camera[0], camera[1], camera[2], camera[3], samples.size(1),
                   samples.size(0), channels, n_points, channel_weights.data(), huber_delta, max_depth_residual,
                   max_depth_slope, cap};
  std::vector<Sums> sums(at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(samples.scalar_type(), "alignment_normal_equations", [&] {
    const auto* pts = points.data_ptr<scalar_t>();
    const auto* rf = ref.data_ptr<scalar_t>();
    const auto* smp = samples.data_ptr<scalar_t>();
    at::parallel_for(0, n_points, 1024, [&](int64_t begin, int64_t end) {
      Sums local;
      std::vector<double> values(3 * channels);
      for (int64_t n = begin; n < end; ++n) add_point(pb, pts + 3 * n, rf, n, smp, values.data(), local);
      Sums& s = sums[at::get_thread_num()];
      for (int i = 0; i < 36; ++i) s.h[i] += local.h[i];
      for (int i = 0; i < 6; ++i) s.g[i] += local.g[i];
      s.cost += local.cost;
      s.valid += local.valid;
    });
  });
  auto h = torch::zeros({6, 6}, torch::kFloat64), g = torch::zeros({6}, torch::kFloat64);
  auto* hp = h.data_ptr<double>();
  auto* gp = g.data_ptr<double>();
  double cost = 0.0;
  int64_t valid = 0;
  for (const Sums& s : sums) {
    for (int i = 0; i < 6; ++i) {
      for (int j = i; j < 6; ++j) hp[i * 6 + j] += s.h[i * 6 + j];
      gp[i] += s.g[i];
    }
    cost += s.cost;
    valid += s.valid;
  }
  for (int i = 0; i < 6; ++i) {
    for (int j = 0; j < i; ++j) hp[i * 6 + j] = hp[j * 6 + i];
  }
  return {h, g, cost, valid};
}

}  // namespace gausem
