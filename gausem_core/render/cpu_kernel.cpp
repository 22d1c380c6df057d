// Compiled CPU rasteriser of screen Gaussians: the model of gausem_core/render/__init__.py in plain loops.
//
// forward: the Gaussians, listed front to back, emit their (pixel, alpha >= 1/255) pairs; a counting sort by pixel
// keeps them front to back within each pixel (no comparison sort); each pixel is then composited in one pass.
// backward: per pixel, a forward walk for the transmittances and a backward walk for the suffix sums
// S_i = sum_{k>i} w_k h_k give dL/dalpha_i = T_i h_i - S_i / (1 - alpha_i), as in composite.py. Per-thread gradient
// buffers avoid atomics. Transmittances and suffix sums are accumulated in double.
#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr int64_t kGrain = 256;  // pixels per parallel chunk

struct Screen {
  torch::Tensor u, v, inv_var_x, inv_var_y, opacity, features;
};

void check_screen(const Screen& s) {
  const auto m = s.u.size(0);
  for (const auto& t : {s.v, s.inv_var_x, s.inv_var_y, s.opacity}) {
    TORCH_CHECK(t.dim() == 1 && t.size(0) == m, "screen tensors must all have M rows");
  }
  TORCH_CHECK(s.features.dim() == 2 && s.features.size(0) == m, "features must be (M, C)");
}

// (pixel offsets [n_pixels + 1], gaussian [P] int32, unclamped alpha [P]), pairs sorted by pixel, front to back.
std::vector<torch::Tensor> build_pairs(const Screen& s, const torch::Tensor& order, const torch::Tensor& x0,
                                       const torch::Tensor& x1, const torch::Tensor& y0, const torch::Tensor& y1,
                                       int64_t width, int64_t height) {
  const int64_t n_pixels = width * height;
  auto offsets = torch::zeros({n_pixels + 1}, torch::kInt64);
  torch::Tensor gaussian_out, alpha_out;
  AT_DISPATCH_FLOATING_TYPES(s.u.scalar_type(), "build_pairs", [&] {
    const auto u = s.u.accessor<scalar_t, 1>();
    const auto v = s.v.accessor<scalar_t, 1>();
    const auto ivx = s.inv_var_x.accessor<scalar_t, 1>();
    const auto ivy = s.inv_var_y.accessor<scalar_t, 1>();
    const auto op = s.opacity.accessor<scalar_t, 1>();
    const auto ord = order.accessor<int64_t, 1>();
    const auto bx0 = x0.accessor<int64_t, 1>(), bx1 = x1.accessor<int64_t, 1>();
    const auto by0 = y0.accessor<int64_t, 1>(), by1 = y1.accessor<int64_t, 1>();
    const scalar_t alpha_min = static_cast<scalar_t>(kAlphaMin);
    std::vector<int32_t> gen_pixel, gen_gaussian;
    std::vector<scalar_t> gen_alpha;
    auto* count = offsets.data_ptr<int64_t>() + 1;
    for (int64_t k = 0; k < ord.size(0); ++k) {
      const int64_t g = ord[k];
      const scalar_t gu = u[g], gv = v[g], ax = ivx[g], ay = ivy[g], o = op[g];
      for (int64_t y = by0[g]; y <= by1[g]; ++y) {
        const scalar_t dy = static_cast<scalar_t>(y) + scalar_t(0.5) - gv;
        const scalar_t qy = dy * dy * ay;
        for (int64_t x = bx0[g]; x <= bx1[g]; ++x) {
          const scalar_t dx = static_cast<scalar_t>(x) + scalar_t(0.5) - gu;
          const scalar_t alpha = o * std::exp(scalar_t(-0.5) * (dx * dx * ax + qy));
          if (alpha >= alpha_min) {
            const int64_t pixel = y * width + x;
            gen_pixel.push_back(static_cast<int32_t>(pixel));
            gen_gaussian.push_back(static_cast<int32_t>(g));
            gen_alpha.push_back(alpha);
            ++count[pixel];
          }
        }
      }
    }
    auto* off = offsets.data_ptr<int64_t>();
    for (int64_t p = 0; p < n_pixels; ++p) off[p + 1] += off[p];
    const auto n_pairs = static_cast<int64_t>(gen_pixel.size());
    gaussian_out = torch::empty({n_pairs}, torch::kInt32);
    alpha_out = torch::empty({n_pairs}, s.u.options());
    auto* g_out = gaussian_out.data_ptr<int32_t>();
    auto* a_out = alpha_out.data_ptr<scalar_t>();
    std::vector<int64_t> cursor(off, off + n_pixels);
    for (int64_t i = 0; i < n_pairs; ++i) {  // stable: generation order is front to back
      const int64_t at = cursor[gen_pixel[i]]++;
      g_out[at] = gen_gaussian[i];
      a_out[at] = gen_alpha[i];
    }
  });
  return {offsets, gaussian_out, alpha_out};
}

std::vector<torch::Tensor> rasterize_forward(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x,
                                             torch::Tensor inv_var_y, torch::Tensor opacity, torch::Tensor features,
                                             torch::Tensor order, torch::Tensor x0, torch::Tensor x1,
                                             torch::Tensor y0, torch::Tensor y1, int64_t width, int64_t height) {
  const Screen s{u.contiguous(), v.contiguous(), inv_var_x.contiguous(), inv_var_y.contiguous(),
                 opacity.contiguous(), features.contiguous()};
  check_screen(s);
  auto pairs = build_pairs(s, order.contiguous(), x0.contiguous(), x1.contiguous(), y0.contiguous(),
                           y1.contiguous(), width, height);
  const int64_t n_pixels = width * height, channels = s.features.size(1);
  auto image = torch::zeros({n_pixels, channels + 1}, s.u.options());
  AT_DISPATCH_FLOATING_TYPES(s.u.scalar_type(), "rasterize_forward", [&] {
    const auto* off = pairs[0].data_ptr<int64_t>();
    const auto* gauss = pairs[1].data_ptr<int32_t>();
    const auto* alpha = pairs[2].data_ptr<scalar_t>();
    const auto* feat = s.features.data_ptr<scalar_t>();
    auto* out = image.data_ptr<scalar_t>();
    at::parallel_for(0, n_pixels, kGrain, [&](int64_t begin, int64_t end) {
      std::vector<double> acc(channels + 1);
      for (int64_t p = begin; p < end; ++p) {
        std::fill(acc.begin(), acc.end(), 0.0);
        double transmittance = 1.0;
        for (int64_t i = off[p]; i < off[p + 1]; ++i) {
          const double a = std::min(static_cast<double>(alpha[i]), kAlphaMax);
          const double w = a * transmittance;
          const scalar_t* f = feat + static_cast<int64_t>(gauss[i]) * channels;
          for (int64_t c = 0; c < channels; ++c) acc[c] += w * f[c];
          acc[channels] += w;
          transmittance *= 1.0 - a;
        }
        for (int64_t c = 0; c <= channels; ++c) out[p * (channels + 1) + c] = static_cast<scalar_t>(acc[c]);
      }
    });
  });
  return {image, pairs[0], pairs[1], pairs[2]};
}

// Gradients w.r.t. (u, v, inv_var_x, inv_var_y, opacity, features) from dL/d(image) of shape (n_pixels, C + 1).
std::vector<torch::Tensor> rasterize_backward(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x,
                                              torch::Tensor inv_var_y, torch::Tensor opacity, torch::Tensor features,
                                              torch::Tensor offsets, torch::Tensor gaussian, torch::Tensor alpha,
                                              torch::Tensor grad_image, int64_t width) {
  const Screen s{u.contiguous(), v.contiguous(), inv_var_x.contiguous(), inv_var_y.contiguous(),
                 opacity.contiguous(), features.contiguous()};
  check_screen(s);
  grad_image = grad_image.contiguous();
  const int64_t m = s.u.size(0), channels = s.features.size(1), n_pixels = offsets.size(0) - 1;
  const int64_t stride = 5 + channels;  // per Gaussian: u, v, inv_var_x, inv_var_y, opacity, features
  TORCH_CHECK(grad_image.size(0) == n_pixels && grad_image.size(1) == channels + 1, "grad_image has the wrong shape");
  const int n_threads = at::get_num_threads();
  auto buffers = torch::zeros({n_threads, m * stride}, torch::kFloat64);
  AT_DISPATCH_FLOATING_TYPES(s.u.scalar_type(), "rasterize_backward", [&] {
    const auto* off = offsets.data_ptr<int64_t>();
    const auto* gauss = gaussian.data_ptr<int32_t>();
    const auto* al = alpha.data_ptr<scalar_t>();
    const auto* feat = s.features.data_ptr<scalar_t>();
    const auto* gu = s.u.data_ptr<scalar_t>();
    const auto* gv = s.v.data_ptr<scalar_t>();
    const auto* ax = s.inv_var_x.data_ptr<scalar_t>();
    const auto* ay = s.inv_var_y.data_ptr<scalar_t>();
    const auto* op = s.opacity.data_ptr<scalar_t>();
    const auto* grad = grad_image.data_ptr<scalar_t>();
    auto* all_buffers = buffers.data_ptr<double>();
    at::parallel_for(0, n_pixels, kGrain, [&](int64_t begin, int64_t end) {
      double* acc = all_buffers + static_cast<int64_t>(at::get_thread_num()) * m * stride;
      std::vector<double> trans, h;
      for (int64_t p = begin; p < end; ++p) {
        const int64_t first = off[p], n = off[p + 1] - first;
        if (n == 0) continue;
        const scalar_t* gp = grad + p * (channels + 1);
        trans.resize(n);
        h.resize(n);
        double transmittance = 1.0;
        for (int64_t k = 0; k < n; ++k) {
          const int64_t i = first + k;
          const scalar_t* f = feat + static_cast<int64_t>(gauss[i]) * channels;
          double hk = gp[channels];
          for (int64_t c = 0; c < channels; ++c) hk += static_cast<double>(f[c]) * gp[c];
          trans[k] = transmittance;
          h[k] = hk;
          transmittance *= 1.0 - std::min(static_cast<double>(al[i]), kAlphaMax);
        }
        const double col = static_cast<double>(p % width) + 0.5, row = static_cast<double>(p / width) + 0.5;
        double behind = 0.0;  // S_k = sum over the pairs behind k of w h
        for (int64_t k = n - 1; k >= 0; --k) {
          const int64_t i = first + k, g = gauss[i];
          const double a_raw = al[i], a = std::min(a_raw, kAlphaMax), w = a * trans[k];
          double* gacc = acc + g * stride;
          for (int64_t c = 0; c < channels; ++c) gacc[5 + c] += w * gp[c];
          if (a_raw <= kAlphaMax) {  // a clamped alpha has no gradient
            const double grad_alpha = trans[k] * h[k] - behind / (1.0 - a);
            const double g_q = grad_alpha * a_raw;  // dL/d(-q/2)
            const double dx = col - gu[g], dy = row - gv[g];
            gacc[0] += g_q * ax[g] * dx;
            gacc[1] += g_q * ay[g] * dy;
            gacc[2] += -0.5 * g_q * dx * dx;
            gacc[3] += -0.5 * g_q * dy * dy;
            gacc[4] += g_q / op[g];
          }
          behind += w * h[k];
        }
      }
    });
  });
  auto total = buffers.sum(0).view({m, stride}).to(s.u.scalar_type());
  return {total.select(1, 0), total.select(1, 1), total.select(1, 2), total.select(1, 3), total.select(1, 4),
          total.narrow(1, 5, channels).contiguous()};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rasterize_forward", &rasterize_forward, "composite screen Gaussians: (image, offsets, gaussian, alpha)");
  m.def("rasterize_backward", &rasterize_backward, "gradients of rasterize_forward's image");
}
