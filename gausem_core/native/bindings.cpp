// Python bindings of the compiled CPU kernels (kernels.h).
#include "kernels.h"

// Each kernel releases the interpreter lock while it runs, so that the tracker and the mapping worker (two Python
// threads, gausem_core/slam/worker.py) compute at once.
PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  using release = pybind11::call_guard<pybind11::gil_scoped_release>;
  m.def("rasterize_forward", &gausem::rasterize_forward,
        "composite screen Gaussians: (image, offsets, slot, alpha)", release());
  m.def("rasterize_backward", &gausem::rasterize_backward, "gradients of rasterize_forward's image", release());
  m.def("rasterize_image", &gausem::rasterize_image, "rasterize_forward's image alone (no gradients)", release());
  m.def("depth_order", &gausem::depth_order, "indices of the kept Gaussians front to back (stable radix sort)",
        release());
  m.def("alignment_normal_equations", &gausem::alignment_normal_equations,
        "direct alignment: (H, g, summed truncated cost, valid points) of one Gauss-Newton step", release());
  m.def("alignment_level", &gausem::alignment_level,
        "direct alignment: (motion, mean cost before the last step) after a level of Gauss-Newton steps", release());
}
