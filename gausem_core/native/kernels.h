// The compiled CPU kernels of GauSem (built by gausem_core/native/__init__.py into one extension module).
#pragma once

#include <torch/extension.h>

#include <tuple>
#include <vector>

namespace gausem {

// raster.cpp: the renderer's compositing (gausem_core/render/cpu_backend.py)
std::vector<torch::Tensor> rasterize_forward(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x,
                                             torch::Tensor inv_var_y, torch::Tensor opacity, torch::Tensor features,
                                             torch::Tensor order, torch::Tensor x0, torch::Tensor x1,
                                             torch::Tensor y0, torch::Tensor y1, int64_t width, int64_t height);
std::vector<torch::Tensor> rasterize_backward(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x,
                                              torch::Tensor inv_var_y, torch::Tensor opacity, torch::Tensor features,
                                              torch::Tensor order, torch::Tensor offsets, torch::Tensor slots,
                                              torch::Tensor alpha, torch::Tensor grad_image, int64_t width);
torch::Tensor rasterize_image(torch::Tensor u, torch::Tensor v, torch::Tensor inv_var_x, torch::Tensor inv_var_y,
                              torch::Tensor opacity, torch::Tensor features, torch::Tensor order, torch::Tensor x0,
                              torch::Tensor x1, torch::Tensor y0, torch::Tensor y1, int64_t width, int64_t height);
torch::Tensor depth_order(torch::Tensor depth, torch::Tensor keep);

// alignment.cpp: Gauss-Newton normal equations of direct alignment (gausem_core/slam/direct_alignment.py)
std::tuple<torch::Tensor, torch::Tensor, double, int64_t> alignment_normal_equations(
    torch::Tensor points, torch::Tensor ref, torch::Tensor motion, torch::Tensor samples, std::vector<double> camera,
    std::vector<double> channel_weights, double huber_delta, double max_depth_residual, double max_depth_slope,
    double cap);
std::tuple<torch::Tensor, double> alignment_level(
    torch::Tensor points, torch::Tensor ref, torch::Tensor motion, torch::Tensor samples, std::vector<double> camera,
    std::vector<double> channel_weights, double huber_delta, double max_depth_residual, double max_depth_slope,
    double cap, int64_t iterations, double damping, double min_step);

}  // namespace gausem
