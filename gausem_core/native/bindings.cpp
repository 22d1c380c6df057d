// Python bindings of the compiled CPU kernels (kernels.h).
#include "kernels.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("rasterize_forward", &gausem::rasterize_forward,
        "composite screen Gaussians: (image, offsets, slot, alpha)");
  m.def("rasterize_backward", &gausem::rasterize_backward, "gradients of rasterize_forward's image");
  m.def("depth_order", &gausem::depth_order, "indices of the kept Gaussians front to back (stable radix sort)");
  m.def("alignment_normal_equations", &gausem::alignment_normal_equations,
        "direct alignment: (H, g, summed truncated cost, valid points) of one Gauss-Newton step");
}
