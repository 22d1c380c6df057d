// Compiled CPU rasteriser of screen Gaussians: the model of gausem_core/render/__init__.py in plain loops.
//
// depth_order: the front-to-back order of the Gaussians by a stable radix sort of their depths.
// forward: the Gaussians are bucketed once by chunk of rows; per chunk, its Gaussians, front to back, emit their
// (pixel, alpha >= 1/255) pairs; a counting sort by pixel keeps them front to back within each pixel (no comparison
// sort); each pixel is then composited in one pass.
// image: the forward's image alone, composited as the Gaussians are visited (no pairs kept, no sort).
// backward: per pixel, a forward walk for the transmittances and a backward walk for the suffix sums
// S_i = sum_{k>i} w_k h_k give dL/dalpha_i = T_i h_i - S_i / (1 - alpha_i), as in composite.py. Per-thread gradient
// buffers avoid atomics. Transmittances and suffix sums are accumulated in double. Pairs name a Gaussian by its slot
// in the depth order (only Gaussians with a footprint have one), so the backward's buffers and their reduction scale
// with the Gaussians in view, not with the whole cloud.
#include "kernels.h"

#include <ATen/Parallel.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr int64_t kGrain = 256;  // pixels per parallel task in the backward
constexpr int64_t kRowsPerChunk = 8;  // image rows per parallel task in the forward

struct Screen {
  torch::Tensor u, v, inv_var_x, inv_var_y, opacity, features;
};

// The screen tensors, contiguous and checked: M rows each, features (M, C).
Screen screen_of(const torch::Tensor& u, const torch::Tensor& v, const torch::Tensor& inv_var_x,
                 const torch::Tensor& inv_var_y, const torch::Tensor& opacity, const torch::Tensor& features) {
  const Screen s{u.contiguous(), v.contiguous(), inv_var_x.contiguous(), inv_var_y.contiguous(),
                 opacity.contiguous(), features.contiguous()};
  const auto m = s.u.size(0);
  for (const auto& t : {s.v, s.inv_var_x, s.inv_var_y, s.opacity}) {
    TORCH_CHECK(t.dim() == 1 && t.size(0) == m, "screen tensors must all have M rows");
  }
  TORCH_CHECK(s.features.dim() == 2 && s.features.size(0) == m, "features must be (M, C)");
  return s;
}

// A Gaussian's alpha is separable: opacity * exp(-dx^2 ax / 2) * exp(-dy^2 ay / 2). Its column factors over its box
// [xa, xb] go to ``out`` (one exp per column, not per pixel); each row then costs one exp.
template <typename scalar_t>
void column_factors(scalar_t gu, scalar_t ax, int64_t xa, int64_t xb, std::vector<scalar_t>& out) {
  out.resize(std::max<int64_t>(xb - xa + 1, 0));
  for (int64_t x = xa; x <= xb; ++x) {
    const scalar_t dx = static_cast<scalar_t>(x) + scalar_t(0.5) - gu;
    out[x - xa] = std::exp(scalar_t(-0.5) * dx * dx * ax);
  }
}

template <typename scalar_t>
scalar_t row_factor(int64_t y, scalar_t gv, scalar_t ay, scalar_t opacity) {
  const scalar_t dy = static_cast<scalar_t>(y) + scalar_t(0.5) - gv;
  return opacity * std::exp(scalar_t(-0.5) * dy * dy * ay);
}

// The pairs and the composited pixels of rows [row0, row1): Gaussians visited front to back emit (pixel, alpha)
// pairs; a counting sort by pixel keeps each pixel's pairs in that order (no comparison sort).
template <typename scalar_t>
struct RowChunk {
  int64_t row0 = 0, row1 = 0;
  std::vector<int64_t> offsets;  // per pixel of the chunk (row-major), + 1
  std::vector<int32_t> slot;  // the pair's Gaussian as its position in the depth order
  std::vector<scalar_t> alpha;  // unclamped
};

template <typename scalar_t>
void fill_chunk(RowChunk<scalar_t>& chunk, const Screen& s, const std::vector<int32_t>& members,
                const int64_t* ord, const int64_t* x0, const int64_t* x1, const int64_t* y0, const int64_t* y1,
                int64_t width, std::vector<int32_t>& gen_pixel, std::vector<int32_t>& gen_slot,
                std::vector<scalar_t>& gen_alpha) {
  const auto* u = s.u.data_ptr<scalar_t>();
  const auto* v = s.v.data_ptr<scalar_t>();
  const auto* ivx = s.inv_var_x.data_ptr<scalar_t>();
  const auto* ivy = s.inv_var_y.data_ptr<scalar_t>();
  const auto* op = s.opacity.data_ptr<scalar_t>();
  const scalar_t alpha_min = static_cast<scalar_t>(kAlphaMin);
  const int64_t n_pixels = (chunk.row1 - chunk.row0) * width;
  gen_pixel.clear();
  gen_slot.clear();
  gen_alpha.clear();
  chunk.offsets.assign(n_pixels + 1, 0);
  auto* count = chunk.offsets.data() + 1;
  std::vector<scalar_t> columns;
  for (const int32_t k : members) {
    const int64_t g = ord[k];
    const int64_t ya = std::max(y0[g], chunk.row0), yb = std::min(y1[g], chunk.row1 - 1), xa = x0[g], xb = x1[g];
    column_factors(u[g], ivx[g], xa, xb, columns);
    for (int64_t y = ya; y <= yb; ++y) {
      const scalar_t row = row_factor(y, v[g], ivy[g], op[g]);
      const int64_t row_start = (y - chunk.row0) * width;
      for (int64_t x = xa; x <= xb; ++x) {
        const scalar_t alpha = row * columns[x - xa];
        if (alpha >= alpha_min) {
          gen_pixel.push_back(static_cast<int32_t>(row_start + x));
          gen_slot.push_back(k);
          gen_alpha.push_back(alpha);
          ++count[row_start + x];
        }
      }
    }
  }
  auto* off = chunk.offsets.data();
  for (int64_t p = 0; p < n_pixels; ++p) off[p + 1] += off[p];
  const auto n_pairs = static_cast<int64_t>(gen_pixel.size());
  chunk.slot.resize(n_pairs);
  chunk.alpha.resize(n_pairs);
  std::vector<int64_t> cursor(off, off + n_pixels);
  for (int64_t i = 0; i < n_pairs; ++i) {  // stable: generation order is front to back
    const int64_t at = cursor[gen_pixel[i]]++;
    chunk.slot[at] = gen_slot[i];
    chunk.alpha[at] = gen_alpha[i];
  }
}

template <typename scalar_t>
void composite_chunk(const RowChunk<scalar_t>& chunk, const scalar_t* feat, const int64_t* ord, int64_t channels,
                     int64_t width, scalar_t* out) {
  std::vector<double> acc(channels + 1);
  const int64_t n_pixels = (chunk.row1 - chunk.row0) * width;
  for (int64_t p = 0; p < n_pixels; ++p) {
    std::fill(acc.begin(), acc.end(), 0.0);
    double transmittance = 1.0;
    for (int64_t i = chunk.offsets[p]; i < chunk.offsets[p + 1]; ++i) {
      const double a = std::min(static_cast<double>(chunk.alpha[i]), kAlphaMax);
      const double w = a * transmittance;
      const scalar_t* f = feat + ord[chunk.slot[i]] * channels;
      for (int64_t c = 0; c < channels; ++c) acc[c] += w * f[c];
      acc[channels] += w;
      transmittance *= 1.0 - a;
    }
    scalar_t* o = out + (chunk.row0 * width + p) * (channels + 1);
    for (int64_t c = 0; c <= channels; ++c) o[c] = static_cast<scalar_t>(acc[c]);
  }
}

// The image of rows [row0, row1) without keeping pairs (no gradients wanted): the Gaussians, front to back, are
// composited straight into per-pixel sums and transmittances, so each pixel sums the same terms in the same order as
// fill_chunk + composite_chunk do.
template <typename scalar_t>
void composite_rows(int64_t row0, int64_t row1, const Screen& s, const std::vector<int32_t>& members,
                    const int64_t* ord, const int64_t* x0, const int64_t* x1, const int64_t* y0, const int64_t* y1,
                    int64_t width, std::vector<double>& acc, std::vector<double>& transmittance, scalar_t* out) {
  const auto* u = s.u.data_ptr<scalar_t>();
  const auto* v = s.v.data_ptr<scalar_t>();
  const auto* ivx = s.inv_var_x.data_ptr<scalar_t>();
  const auto* ivy = s.inv_var_y.data_ptr<scalar_t>();
  const auto* op = s.opacity.data_ptr<scalar_t>();
  const auto* feat = s.features.data_ptr<scalar_t>();
  const int64_t channels = s.features.size(1), n_pixels = (row1 - row0) * width;
  const scalar_t alpha_min = static_cast<scalar_t>(kAlphaMin);
  acc.assign(n_pixels * (channels + 1), 0.0);
  transmittance.assign(n_pixels, 1.0);
  std::vector<scalar_t> columns;
  std::vector<double> gaussian_features(channels);
  double* __restrict sums = acc.data();
  double* __restrict through = transmittance.data();
  for (const int32_t k : members) {
    const int64_t g = ord[k];
    const int64_t ya = std::max(y0[g], row0), yb = std::min(y1[g], row1 - 1), xa = x0[g], xb = x1[g];
    for (int64_t c = 0; c < channels; ++c) gaussian_features[c] = static_cast<double>(feat[g * channels + c]);
    const double* __restrict f = gaussian_features.data();
    column_factors(u[g], ivx[g], xa, xb, columns);
    const scalar_t* __restrict column = columns.data();
    for (int64_t y = ya; y <= yb; ++y) {
      const scalar_t row = row_factor(y, v[g], ivy[g], op[g]);
      const int64_t row_start = (y - row0) * width;
      for (int64_t x = xa; x <= xb; ++x) {
        const scalar_t alpha = row * column[x - xa];
        if (alpha < alpha_min) continue;
        const int64_t p = row_start + x;
        const double a = std::min(static_cast<double>(alpha), kAlphaMax), w = a * through[p];
        double* __restrict sum = sums + p * (channels + 1);
        for (int64_t c = 0; c < channels; ++c) sum[c] += w * f[c];
        sum[channels] += w;
        through[p] *= 1.0 - a;
      }
    }
  }
  scalar_t* o = out + row0 * width * (channels + 1);
  for (int64_t i = 0; i < n_pixels * (channels + 1); ++i) o[i] = static_cast<scalar_t>(acc[i]);
}

// The Gaussians' slots in the depth order bucketed by the chunk of kRowsPerChunk rows their boxes meet.
std::vector<std::vector<int32_t>> chunk_members(const torch::Tensor& order, const torch::Tensor& y0,
                                                const torch::Tensor& y1, int64_t height) {
  std::vector<std::vector<int32_t>> members((height + kRowsPerChunk - 1) / kRowsPerChunk);
  const auto* ord = order.data_ptr<int64_t>();
  const auto* top = y0.data_ptr<int64_t>();
  const auto* bottom = y1.data_ptr<int64_t>();
  for (int64_t k = 0; k < order.size(0); ++k) {
    const int64_t g = ord[k];
    TORCH_CHECK(top[g] > bottom[g] || (top[g] >= 0 && bottom[g] < height), "box rows outside the image");
    for (int64_t c = top[g] / kRowsPerChunk; c <= bottom[g] / kRowsPerChunk; ++c) {
      members[c].push_back(static_cast<int32_t>(k));
    }
  }
  return members;
}

// Indices of the Gaussians with keep[i], front to back, stable in the index: an LSD radix sort (8-bit digits) of the
// depths' bit patterns, which order like positive floats. Torch's CPU sort is a comparison sort at these sizes.
template <typename scalar_t>
torch::Tensor radix_depth_order(const torch::Tensor& depth, const torch::Tensor& keep) {
  using key_t = std::conditional_t<sizeof(scalar_t) == 8, uint64_t, uint32_t>;
  const auto* d = depth.data_ptr<scalar_t>();
  const auto* k = keep.data_ptr<bool>();
  std::vector<int64_t> index, index_tmp;
  std::vector<key_t> keys, keys_tmp;
  for (int64_t i = 0; i < depth.size(0); ++i) {
    if (!k[i]) continue;
    TORCH_CHECK(d[i] > 0, "depth_order: depths must be positive");
    key_t key;
    std::memcpy(&key, d + i, sizeof(key));
    index.push_back(i);
    keys.push_back(key);
  }
  const auto n = static_cast<int64_t>(index.size());
  index_tmp.resize(n);
  keys_tmp.resize(n);
  for (unsigned shift = 0; shift < 8 * sizeof(key_t); shift += 8) {
    int64_t start[257] = {0};
    for (const key_t key : keys) ++start[((key >> shift) & 0xFF) + 1];
    if (std::any_of(start + 1, start + 257, [n](int64_t c) { return c == n; })) continue;  // one digit: no-op pass
    for (int b = 0; b < 256; ++b) start[b + 1] += start[b];
    for (int64_t i = 0; i < n; ++i) {
      const int64_t at = start[(keys[i] >> shift) & 0xFF]++;
      index_tmp[at] = index[i];
      keys_tmp[at] = keys[i];
    }
    index.swap(index_tmp);
    keys.swap(keys_tmp);
  }
  auto order = torch::empty({n}, torch::kInt64);
  std::copy(index.begin(), index.end(), order.data_ptr<int64_t>());
  return order;
}

}  // namespace

namespace gausem {

// (image (n_pixels, C + 1), pixel offsets [n_pixels + 1], slot [P] int32 (into order), unclamped alpha [P]): the
// pairs sorted by pixel, front to back within a pixel. Chunks of rows are independent, so they run in parallel.
std::vector<torch::Tensor> rasterize_forward(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x,
                                             torch::Tensor inv_var_y, torch::Tensor opacity, torch::Tensor features,
                                             torch::Tensor order, torch::Tensor x0, torch::Tensor x1,
                                             torch::Tensor y0, torch::Tensor y1, int64_t width, int64_t height) {
  const Screen s = screen_of(u, v, inv_var_x, inv_var_y, opacity, features);
  order = order.contiguous();
  x0 = x0.contiguous(), x1 = x1.contiguous(), y0 = y0.contiguous(), y1 = y1.contiguous();
  const int64_t n_pixels = width * height, channels = s.features.size(1);
  const int64_t n_chunks = (height + kRowsPerChunk - 1) / kRowsPerChunk;
  auto image = torch::zeros({n_pixels, channels + 1}, s.u.options());
  auto offsets = torch::empty({n_pixels + 1}, torch::kInt64);
  torch::Tensor slot_out, alpha_out;
  AT_DISPATCH_FLOATING_TYPES(s.u.scalar_type(), "rasterize_forward", [&] {
    std::vector<RowChunk<scalar_t>> chunks(n_chunks);
    const auto members = chunk_members(order, y0, y1, height);
    const auto* ord = order.data_ptr<int64_t>();
    at::parallel_for(0, n_chunks, 1, [&](int64_t begin, int64_t end) {
      std::vector<int32_t> gen_pixel, gen_slot;
      std::vector<scalar_t> gen_alpha;
      for (int64_t c = begin; c < end; ++c) {
        chunks[c].row0 = c * kRowsPerChunk;
        chunks[c].row1 = std::min(height, chunks[c].row0 + kRowsPerChunk);
        fill_chunk(chunks[c], s, members[c], ord, x0.data_ptr<int64_t>(), x1.data_ptr<int64_t>(),
                   y0.data_ptr<int64_t>(), y1.data_ptr<int64_t>(), width, gen_pixel, gen_slot, gen_alpha);
        composite_chunk(chunks[c], s.features.data_ptr<scalar_t>(), ord, channels, width,
                        image.data_ptr<scalar_t>());
      }
    });
    int64_t n_pairs = 0;
    for (const auto& chunk : chunks) n_pairs += static_cast<int64_t>(chunk.slot.size());
    slot_out = torch::empty({n_pairs}, torch::kInt32);
    alpha_out = torch::empty({n_pairs}, s.u.options());
    auto* off = offsets.data_ptr<int64_t>();
    int64_t at = 0;
    for (const auto& chunk : chunks) {
      const int64_t first_pixel = chunk.row0 * width, n = static_cast<int64_t>(chunk.slot.size());
      const int64_t chunk_pixels = static_cast<int64_t>(chunk.offsets.size()) - 1;
      for (int64_t p = 0; p < chunk_pixels; ++p) off[first_pixel + p] = at + chunk.offsets[p];
      std::copy(chunk.slot.begin(), chunk.slot.end(), slot_out.data_ptr<int32_t>() + at);
      std::copy(chunk.alpha.begin(), chunk.alpha.end(), alpha_out.data_ptr<scalar_t>() + at);
      at += n;
    }
    off[n_pixels] = at;
  });
  return {image, offsets, slot_out, alpha_out};
}

// The image (n_pixels, C + 1) of rasterize_forward, without the pairs a backward needs.
torch::Tensor rasterize_image(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x, torch::Tensor inv_var_y,
                              torch::Tensor opacity, torch::Tensor features, torch::Tensor order, torch::Tensor x0,
                              torch::Tensor x1, torch::Tensor y0, torch::Tensor y1, int64_t width, int64_t height) {
  const Screen s = screen_of(u, v, inv_var_x, inv_var_y, opacity, features);
  order = order.contiguous();
  x0 = x0.contiguous(), x1 = x1.contiguous(), y0 = y0.contiguous(), y1 = y1.contiguous();
  const int64_t n_chunks = (height + kRowsPerChunk - 1) / kRowsPerChunk;
  auto image = torch::empty({width * height, s.features.size(1) + 1}, s.u.options());
  const auto members = chunk_members(order, y0, y1, height);
  AT_DISPATCH_FLOATING_TYPES(s.u.scalar_type(), "rasterize_image", [&] {
    at::parallel_for(0, n_chunks, 1, [&](int64_t begin, int64_t end) {
      std::vector<double> acc, transmittance;
      for (int64_t c = begin; c < end; ++c) {
        composite_rows(c * kRowsPerChunk, std::min(height, (c + 1) * kRowsPerChunk), s, members[c],
                       order.data_ptr<int64_t>(), x0.data_ptr<int64_t>(), x1.data_ptr<int64_t>(),
                       y0.data_ptr<int64_t>(), y1.data_ptr<int64_t>(), width, acc, transmittance,
                       image.data_ptr<scalar_t>());
      }
    });
  });
  return image;
}

torch::Tensor depth_order(torch::Tensor depth, torch::Tensor keep) {
  depth = depth.contiguous(), keep = keep.contiguous();
  TORCH_CHECK(depth.dim() == 1 && keep.dim() == 1 && keep.size(0) == depth.size(0), "depth_order: (M,) and (M,)");
  TORCH_CHECK(keep.scalar_type() == torch::kBool, "depth_order: keep must be a bool mask");
  torch::Tensor order;
  AT_DISPATCH_FLOATING_TYPES(depth.scalar_type(), "depth_order",
                             [&] { order = radix_depth_order<scalar_t>(depth, keep); });
  return order;
}

// Gradients w.r.t. (u, v, inv_var_x, inv_var_y, opacity, features) from dL/d(image) of shape (n_pixels, C + 1).
std::vector<torch::Tensor> rasterize_backward(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x,
                                              torch::Tensor inv_var_y, torch::Tensor opacity, torch::Tensor features,
                                              torch::Tensor order, torch::Tensor offsets, torch::Tensor slots,
                                              torch::Tensor alpha, torch::Tensor grad_image, int64_t width) {
  const Screen s = screen_of(u, v, inv_var_x, inv_var_y, opacity, features);
  grad_image = grad_image.contiguous();
  order = order.contiguous();
  const int64_t m = order.size(0), channels = s.features.size(1), n_pixels = offsets.size(0) - 1;
  const int64_t stride = 5 + channels;  // per Gaussian: u, v, inv_var_x, inv_var_y, opacity, features
  TORCH_CHECK(grad_image.size(0) == n_pixels && grad_image.size(1) == channels + 1, "grad_image has the wrong shape");
  const int n_threads = at::get_num_threads();
  auto buffers = torch::zeros({n_threads, m * stride}, torch::kFloat64);  // per slot, not per Gaussian
  auto total = torch::zeros({s.u.size(0), stride}, s.u.options());
  AT_DISPATCH_FLOATING_TYPES(s.u.scalar_type(), "rasterize_backward", [&] {
    const auto* off = offsets.data_ptr<int64_t>();
    const auto* ord = order.data_ptr<int64_t>();
    const auto* slot = slots.data_ptr<int32_t>();
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
          const scalar_t* f = feat + ord[slot[i]] * channels;
          double hk = gp[channels];
          for (int64_t c = 0; c < channels; ++c) hk += static_cast<double>(f[c]) * gp[c];
          trans[k] = transmittance;
          h[k] = hk;
          transmittance *= 1.0 - std::min(static_cast<double>(al[i]), kAlphaMax);
        }
        const double col = static_cast<double>(p % width) + 0.5, row = static_cast<double>(p / width) + 0.5;
        double behind = 0.0;  // S_k = sum over the pairs behind k of w h
        for (int64_t k = n - 1; k >= 0; --k) {
          const int64_t i = first + k, g = ord[slot[i]];
          const double a_raw = al[i], a = std::min(a_raw, kAlphaMax), w = a * trans[k];
          double* gacc = acc + static_cast<int64_t>(slot[i]) * stride;
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
    auto* out = total.data_ptr<scalar_t>();
    at::parallel_for(0, m, 1024, [&](int64_t begin, int64_t end) {  // sum the threads' buffers into the Gaussians
      for (int64_t k = begin; k < end; ++k) {
        scalar_t* row = out + ord[k] * stride;
        for (int64_t j = 0; j < stride; ++j) {
          double sum = 0.0;
          for (int t = 0; t < n_threads; ++t) sum += all_buffers[(t * m + k) * stride + j];
          row[j] = static_cast<scalar_t>(sum);
        }
      }
    });
  });
  return {total.select(1, 0), total.select(1, 1), total.select(1, 2), total.select(1, 3), total.select(1, 4),
          total.narrow(1, 5, channels).contiguous()};
}

}  // namespace gausem
