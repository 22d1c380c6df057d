"""The differentiable Gaussian renderer: analytic footprints, compositing order, depth, a naive reference loop,
gradients (gradcheck), culling and empty views, band processing, the compiled CPU kernel, back-end selection."""
import math
import shutil

import pytest
import torch
import torch.utils.cpp_extension
from rounding import assert_within_rounding

from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core import native
from gausem_core.native import kernel_available as cpu_kernel_available, kernel_error as cpu_kernel_error
from gausem_core.render import RenderOutput, render, select_backend
from gausem_core.render.cpu_backend import rasterize_cpu
from gausem_core.render.projection import project
from gausem_core.render.torch_backend import rasterize_torch

CAM = PinholeCamera(fx=20.0, fy=22.0, cx=8.0, cy=6.0, width=16, height=12)
CPU_BACKENDS = ["torch", pytest.param("cpu", marks=pytest.mark.skipif(
    not cpu_kernel_available(), reason=f"compiled CPU kernel unavailable: {cpu_kernel_error()}"))]


def cloud_of(means, radii, opacities, colors=None, semantics=None, dtype=torch.float64):
    means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
    n = means.shape[0]
    colors = torch.rand(n, 3, dtype=dtype) if colors is None else torch.as_tensor(colors, dtype=dtype)
    semantics = torch.rand(n, 3, dtype=dtype) if semantics is None else torch.as_tensor(semantics, dtype=dtype)
    return GaussianCloud.from_points(means, colors, semantics, torch.as_tensor(radii, dtype=dtype),
                                     torch.as_tensor(opacities, dtype=dtype))


def random_cloud(n, dtype=torch.float64):
    xy = (torch.rand(n, 2, dtype=dtype) - 0.5) * 1.6
    z = 1.5 + torch.rand(n, 1, dtype=dtype)
    return cloud_of(torch.cat([xy * z, z], 1), 0.04 + 0.08 * torch.rand(n, dtype=dtype),
                    0.2 + 0.7 * torch.rand(n, dtype=dtype), dtype=dtype)


def naive_render(cloud, world_to_cam, cam, near=0.01):
    """Per-pixel loop over the Gaussians sorted by depth: the model written out literally."""
    pts = cloud.means @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    order = [i for i in torch.argsort(pts[:, 2], stable=True).tolist() if pts[i, 2] > near]
    out = torch.zeros(cam.height, cam.width, 8, dtype=cloud.dtype)
    for row in range(cam.height):
        for col in range(cam.width):
            transmittance = 1.0
            for i in order:
                x, y, z = pts[i]
                sx, sy = cloud.radii[i] * cam.fx / z, cloud.radii[i] * cam.fy / z
                dx, dy = col + 0.5 - (cam.fx * x / z + cam.cx), row + 0.5 - (cam.fy * y / z + cam.cy)
                alpha = cloud.opacities[i] * torch.exp(-0.5 * (dx**2 / sx**2 + dy**2 / sy**2))
                if alpha < 1 / 255:
                    continue
                alpha = min(float(alpha), 0.99)
                feat = torch.cat([cloud.colors[i], cloud.semantics[i], z[None], torch.ones(1, dtype=cloud.dtype)])
                out[row, col] += alpha * transmittance * feat
                transmittance *= 1 - alpha
    return out


def stacked(out: RenderOutput) -> torch.Tensor:
    return torch.cat([out.color, out.semantic, out.depth[..., None], out.alpha[..., None]], -1)


# the rounded operations behind one Gaussian's term in a pixel (projection, offset, exponent, exp, alpha, the
# transmittance's factor, the product): a pixel of n Gaussians is at most this many times n operations deep
OPERATIONS_PER_GAUSSIAN = 64


def assert_image_within_rounding(image: torch.Tensor, exact: torch.Tensor, gaussians: int):
    """A float32 render within float32's rounding of the float64 render of the same (widened) cloud, pixel by pixel.
    Every channel composites non-negative terms (colours, semantics, depth, alpha), so a pixel's magnitude is its
    value."""
    assert_within_rounding(image, exact, exact.abs(), OPERATIONS_PER_GAUSSIAN * gaussians, image.dtype, "image")


def test_single_gaussian_matches_its_analytic_footprint():
    z, radius, opacity = 2.0, 0.2, 0.8  # sigma_x = 2 px, sigma_y = 2.2 px
    x, y = (10.5 - CAM.cx) * z / CAM.fx, (5.5 - CAM.cy) * z / CAM.fy  # centre exactly on pixel (row 5, col 10)
    out = render(cloud_of([x, y, z], [radius], [opacity], colors=[[1.0, 0.5, 0.25]]), torch.eye(4, dtype=torch.float64), CAM)
    sx, sy = radius * CAM.fx / z, radius * CAM.fy / z
    assert out.alpha[5, 10].item() == pytest.approx(opacity, abs=1e-9)  # peak
    assert out.alpha.argmax().item() == 5 * CAM.width + 10  # position
    assert out.color[5, 10].tolist() == pytest.approx([opacity, opacity / 2, opacity / 4], abs=1e-9)
    assert out.depth[5, 10].item() == pytest.approx(opacity * z, abs=1e-9)
    # 2 px to the right is exactly 1 sigma_x; 1 row down is 1/2.2 sigma_y
    assert out.alpha[5, 12].item() == pytest.approx(opacity * math.exp(-0.5), abs=1e-9)
    assert out.alpha[6, 10].item() == pytest.approx(opacity * math.exp(-0.5 / sy**2), abs=1e-9)
    assert out.alpha[5, 8].item() == pytest.approx(out.alpha[5, 12].item(), abs=1e-12)  # symmetric
    # footprint cut where alpha < 1/255: k = sqrt(2 ln(255 * 0.8)) = 3.26 sigma -> 3.5 sigma out, 3 sigma in
    assert out.alpha[5, 3].item() == 0.0 and out.alpha[5, 4].item() > 0
    assert sx == pytest.approx(2.0)


def test_front_gaussian_occludes_back_and_swapping_depths_flips():
    red, blue = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]

    def centre_colour(z_red, z_blue):
        means = [[(8.5 - CAM.cx) * z / CAM.fx, (6.5 - CAM.cy) * z / CAM.fy, z] for z in (z_red, z_blue)]
        radii = [0.1 * z_red, 0.1 * z_blue]  # same screen size
        out = render(cloud_of(means, radii, [0.9, 0.9], colors=[red, blue]), torch.eye(4, dtype=torch.float64), CAM)
        return out.color[6, 8]

    # pixel (6, 8) is at the centre: front alpha 0.9, back gets 0.9 * 0.1
    near_red = centre_colour(1.0, 2.0)
    assert near_red.tolist() == pytest.approx([0.9, 0.0, 0.09], abs=1e-9)
    assert centre_colour(2.0, 1.0).tolist() == pytest.approx([0.09, 0.0, 0.9], abs=1e-9)


def test_depth_of_a_fronto_parallel_plane():
    z = 2.5
    v, u = torch.meshgrid(torch.arange(-1.0, 13.0), torch.arange(-1.0, 17.0), indexing="ij")
    xs, ys = (u + 0.5 - CAM.cx) * z / CAM.fx, (v + 0.5 - CAM.cy) * z / CAM.fy
    means = torch.stack([xs, ys, torch.full_like(xs, z)], -1).reshape(-1, 3)
    cloud = cloud_of(means, torch.full((means.shape[0],), 1.2 * z / CAM.fx), torch.full((means.shape[0],), 0.7))
    out = render(cloud, torch.eye(4, dtype=torch.float64), CAM)
    assert out.alpha.min().item() > 0.9
    assert torch.allclose(out.depth / out.alpha, torch.full_like(out.depth, z), atol=1e-9)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_agrees_with_a_naive_per_pixel_loop(backend):
    cloud = random_cloud(25)
    pose = se3_exp(torch.tensor([0.05, -0.03, 0.1, 0.02, -0.04, 0.03], dtype=torch.float64))
    assert torch.allclose(stacked(render(cloud, pose, CAM, backend=backend)), naive_render(cloud, pose, CAM),
                          atol=1e-9)
    cloud32, pose32 = cloud.to(dtype=torch.float32), pose.float()
    expected = naive_render(cloud32.to(dtype=torch.float64), pose32.double(), CAM)
    assert_image_within_rounding(stacked(render(cloud32, pose32, CAM, backend=backend)), expected, 25)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("name", ["means", "log_radii", "opacity_logits", "colors", "semantics"])
def test_gradcheck_every_gaussian_parameter(name, backend):
    cloud = random_cloud(4)
    pose = torch.eye(4, dtype=torch.float64)

    def fn(tensor):
        return stacked(render(GaussianCloud(**{**cloud.tensors(), name: tensor}), pose, CAM, backend=backend))

    assert torch.autograd.gradcheck(fn, (getattr(cloud, name).clone().requires_grad_(),), atol=1e-6)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_gradcheck_pose_increment(backend):
    cloud = random_cloud(4)
    base = se3_exp(torch.tensor([0.02, 0.01, -0.05, 0.01, 0.02, -0.01], dtype=torch.float64))
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: stacked(render(cloud, se3_exp(x) @ base, CAM, backend=backend)),
                                    (xi,), atol=1e-6)


def test_culls_gaussians_behind_the_camera_and_before_the_near_plane():
    front = cloud_of([[0.0, 0.0, 2.0]], [0.1], [0.8])
    extra = cloud_of([[0.0, 0.0, -2.0], [0.0, 0.0, 0.05]], [0.1, 0.001], [0.9, 0.9])
    both = GaussianCloud.cat([front, extra])
    eye = torch.eye(4, dtype=torch.float64)
    assert torch.equal(stacked(render(both, eye, CAM, near=0.1)), stacked(render(front, eye, CAM)))
    assert not torch.equal(stacked(render(both, eye, CAM, near=0.01)), stacked(render(front, eye, CAM)))


def assert_zero_images_with_zero_gradients(cloud, pose, backend):
    cloud.requires_grad_()
    pose = pose.clone().requires_grad_()
    out = render(cloud, pose, CAM, backend=backend)
    assert out.color.shape == (12, 16, 3) and out.semantic.shape == (12, 16, 3)
    assert out.depth.shape == (12, 16) and out.alpha.shape == (12, 16)
    assert out.color.dtype == cloud.dtype and out.color.device == cloud.device
    assert stacked(out).abs().sum().item() == 0
    stacked(out).sum().backward()
    for tensor in [*cloud.tensors().values(), pose]:
        assert tensor.grad is not None and tensor.grad.abs().sum().item() == 0


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_empty_cloud_renders_zeros_with_zero_gradients(backend):
    assert_zero_images_with_zero_gradients(GaussianCloud.empty(dtype=torch.float32), torch.eye(4), backend)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_view_without_gaussians_renders_zeros_with_zero_gradients(backend):
    behind_and_aside = cloud_of([[0.0, 0.0, -1.0], [30.0, 0.0, 2.0]], [0.1, 0.1], [0.8, 0.8], dtype=torch.float32)
    assert_zero_images_with_zero_gradients(behind_and_aside, torch.eye(4), backend)


def test_row_bands_give_the_single_band_result_and_gradients():
    cloud = random_cloud(30).requires_grad_()
    pose = torch.eye(4, dtype=torch.float64)
    results = []
    for budget in (1 << 30, 40, 1):  # one band; a few; one row per band
        screen = project(cloud, pose, CAM, 0.01)
        image = rasterize_torch(screen, CAM.width, CAM.height, max_pairs_per_band=budget)
        grads = torch.autograd.grad((image * torch.linspace(0, 1, image.numel()).reshape(image.shape)).sum(),
                                    list(cloud.tensors().values()))
        results.append((image, grads))
    for image, grads in results[1:]:
        assert torch.allclose(image, results[0][0], atol=1e-12)
        for grad, reference in zip(grads, results[0][1]):
            assert torch.allclose(grad, reference, atol=1e-10)


def test_the_compiled_cpu_kernel_builds_where_a_compiler_exists():
    if not (shutil.which("c++") or shutil.which("g++")):
        pytest.skip("no C++ compiler on this machine")
    assert cpu_kernel_available(), cpu_kernel_error()
    assert cpu_kernel_error() is None


def images_and_gradients_of_both_cpu_backends(cloud, pose, cam, threads=2):
    """(image, gradients of every cloud tensor) from the torch back-end and from the compiled kernel."""
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        results = []
        for rasterize in (rasterize_torch, rasterize_cpu):
            tensors = {k: t.detach().clone().requires_grad_() for k, t in cloud.tensors().items()}
            image = rasterize(project(GaussianCloud(**tensors), pose, cam, 0.01), cam.width, cam.height)
            weights = torch.linspace(-1, 1, image.numel(), dtype=image.dtype).reshape(image.shape)
            (image * weights).sum().backward()
            results.append((image.detach(), [t.grad for t in tensors.values()]))
    finally:
        torch.set_num_threads(previous)
    return results


@pytest.mark.skipif(not cpu_kernel_available(), reason="compiled CPU kernel unavailable")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_compiled_kernel_matches_the_torch_backend_on_a_dense_scene_with_two_threads(dtype):
    """Hundreds of Gaussians, many overlapping per pixel and clamped alphas; two threads share the gradient work. Both
    back-ends' images and gradients within ``dtype``'s rounding of the torch back-end's in float64 (the cloud widened
    exactly). A gradient entry sums terms of either sign over the pixels: its tensor's largest entry bounds their
    magnitude."""
    torch.manual_seed(3)
    cam = PinholeCamera(fx=60.0, fy=60.0, cx=24.0, cy=18.0, width=48, height=36)
    xy = (torch.rand(400, 2, dtype=torch.float64) - 0.5) * 1.2
    z = 1.0 + torch.rand(400, 1, dtype=torch.float64)
    opacities = torch.where(torch.rand(400, dtype=torch.float64) < 0.2, 0.995,
                            0.1 + 0.8 * torch.rand(400, dtype=torch.float64))
    cloud = cloud_of(torch.cat([xy * z, z], 1), 0.02 + 0.1 * torch.rand(400, dtype=torch.float64), opacities,
                     dtype=torch.float64).to(dtype=dtype)
    (exact, exact_grads), _ = images_and_gradients_of_both_cpu_backends(cloud.to(dtype=torch.float64),
                                                                        torch.eye(4, dtype=torch.float64), cam)
    assert exact.shape == (36, 48, 8) and exact[..., 7].max() > 0.99  # opaque pixels exist
    # the torch back-end's transmittances are differences of a running sum in float64 over the image's pairs
    gaussians = 400 + (400 * cam.width * cam.height // OPERATIONS_PER_GAUSSIAN if dtype == torch.float64 else 0)
    for image, grads in images_and_gradients_of_both_cpu_backends(cloud, torch.eye(4, dtype=dtype), cam):
        assert_image_within_rounding(image, exact, gaussians)
        for grad, expected in zip(grads, exact_grads):
            assert expected.abs().max() > 0
            assert_within_rounding(grad, expected, expected.abs().max().expand_as(expected),
                                   OPERATIONS_PER_GAUSSIAN * gaussians, dtype, "gradient")


@pytest.mark.skipif(not cpu_kernel_available(), reason="compiled CPU kernel unavailable")
def test_compiled_kernel_matches_the_torch_backend_when_most_gaussians_are_out_of_view():
    """Gaussians behind the camera, before the near plane and beside the image, shuffled among those in view: the
    same image and gradients from both back-ends, and exactly zero gradients for every Gaussian out of view."""
    torch.manual_seed(5)
    in_view = random_cloud(60)
    behind = cloud_of(torch.rand(50, 3, dtype=torch.float64) - torch.tensor([0.5, 0.5, 2.0], dtype=torch.float64),
                      [0.1] * 50, [0.8] * 50)
    near_plane = cloud_of([[0.0, 0.0, 0.005]] * 5, [0.1] * 5, [0.8] * 5)
    beside = cloud_of(torch.tensor([[40.0, 0.0, 2.0], [-40.0, 1.0, 2.0], [0.0, 30.0, 2.0]], dtype=torch.float64),
                      [0.1] * 3, [0.8] * 3)
    shuffle = torch.randperm(118)
    cloud = GaussianCloud(**{k: t[shuffle] for k, t in GaussianCloud.cat([in_view, behind, near_plane, beside])
                             .tensors().items()})
    out_of_view = shuffle >= 60
    (reference, reference_grads), (image, grads) = images_and_gradients_of_both_cpu_backends(
        cloud, torch.eye(4, dtype=torch.float64), CAM)
    assert torch.allclose(image, reference, atol=1e-10) and reference[..., 7].max() > 0.5
    for grad, expected in zip(grads, reference_grads):
        assert torch.allclose(grad, expected, atol=1e-10 * expected.abs().max().item())
        assert grad[~out_of_view].abs().max() > 0 and grad[out_of_view].abs().max() == 0


def test_an_unavailable_kernel_is_a_clear_error_and_auto_falls_back_to_torch(monkeypatch):
    monkeypatch.setattr(native, "_kernel", None)
    monkeypatch.setattr(native, "_error", "RuntimeError: no C++ compiler")
    cloud = random_cloud(2)
    assert select_backend("auto", cloud.device, cloud.dtype) == "torch"
    with pytest.raises(ValueError, match="'cpu' is unavailable.*no C\\+\\+ compiler.*backend='torch'"):
        render(cloud, torch.eye(4, dtype=torch.float64), CAM, backend="cpu")


def test_the_slam_system_builds_the_cpu_kernel_before_its_first_frame(monkeypatch):
    from gausem_core.config import from_flat
    from gausem_core.slam.system import GauSemSLAM

    builds = []

    def fake_build(**kwargs):
        builds.append(kwargs["name"])
        return "kernel"

    monkeypatch.setattr(native, "_kernel", None)
    monkeypatch.setattr(native, "_error", None)
    monkeypatch.setattr(torch.utils.cpp_extension, "load", fake_build)
    GauSemSLAM(from_flat({"backend": "auto"}), "cpu")
    assert builds == [native.KERNEL_NAME] and native._kernel == "kernel"
    GauSemSLAM(from_flat({"backend": "auto"}), "cpu")
    assert len(builds) == 1  # loaded once per process
    monkeypatch.setattr(native, "_kernel", None)
    monkeypatch.setattr(native, "_error", "RuntimeError: no C++ compiler")
    with pytest.raises(ValueError, match="'cpu' is unavailable.*no C\\+\\+ compiler"):
        GauSemSLAM(from_flat({"backend": "cpu"}), "cpu")  # asked for by name: a clear error at once


def test_the_slam_system_renders_once_through_gsplat_before_its_first_frame(monkeypatch):
    """gsplat compiles its CUDA kernels on first use: the system renders one Gaussian at construction."""
    import gausem_core.render as rendering
    from gausem_core.config import from_flat
    from gausem_core.slam.system import GauSemSLAM

    renders = []

    def fake_gsplat(screen, width, height):
        renders.append((screen.u.numel(), width, height))
        return torch.zeros(height, width, 8)

    monkeypatch.setattr(rendering, "select_backend", lambda backend, device, dtype=torch.float32: "gsplat")
    monkeypatch.setattr(rendering, "rasterize_gsplat", fake_gsplat)
    GauSemSLAM(from_flat({"backend": "auto"}), "cpu")
    assert renders == [(1, 16, 16)]


def test_gausem_info_reports_which_cpu_renderer_runs(monkeypatch):
    from gausem_core.tools.info import component_status

    expected = "compiled C++ kernel" if cpu_kernel_available() else f"torch only ({cpu_kernel_error()})"
    assert component_status()["cpu renderer"] == expected.splitlines()[0]
    monkeypatch.setattr(native, "_kernel", None)
    monkeypatch.setattr(native, "_error", "RuntimeError: no C++ compiler")
    assert component_status()["cpu renderer"] == "torch only (RuntimeError: no C++ compiler)"


def test_auto_backend_on_cpu_is_the_compiled_kernel_when_it_builds_and_bad_arguments_raise():
    cloud = random_cloud(2)
    assert select_backend("auto", cloud.device, cloud.dtype) == ("cpu" if cpu_kernel_available() else "torch")
    with pytest.raises(ValueError, match="unknown backend"):
        render(cloud, torch.eye(4, dtype=torch.float64), CAM, backend="opengl")
    with pytest.raises(ValueError, match="world_to_cam"):
        render(cloud, torch.eye(3, dtype=torch.float64), CAM)
    with pytest.raises(ValueError, match="near"):
        render(cloud, torch.eye(4, dtype=torch.float64), CAM, near=0.0)
    with pytest.raises((ValueError, ImportError), match="gsplat"):
        render(cloud, torch.eye(4, dtype=torch.float64), CAM, backend="gsplat")


@pytest.mark.skipif(not cpu_kernel_available(), reason="compiled CPU kernel unavailable")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_compiled_depth_order_is_the_stable_order_of_pairs_depth_order(dtype):
    from gausem_core.render.pairs import Boxes, depth_order
    from gausem_core.render.projection import ScreenGaussians

    g = torch.Generator().manual_seed(5)
    m = 40000
    depth = (torch.randint(1, 400, (m,), generator=g) * 0.01).to(dtype)  # many equal depths: stability matters
    depth[:100] = torch.rand(100, generator=g, dtype=dtype) * 1e3 + 1e-3  # and a spread of magnitudes
    empty = torch.rand(m, generator=g) < 0.2
    x0 = torch.zeros(m, dtype=torch.long)
    boxes = Boxes(x0, x0 - empty.long(), x0, x0)
    screen = ScreenGaussians(*(torch.zeros(m, dtype=dtype),) * 5, depth=depth, features=torch.zeros(m, 1, dtype=dtype))
    expected = depth_order(screen, boxes)
    assert len(expected) == int((~empty).sum())
    assert torch.equal(native.require_kernel().depth_order(depth, boxes.nonempty()), expected)
    with pytest.raises(RuntimeError, match="positive"):
        native.require_kernel().depth_order(-depth, boxes.nonempty())


def test_a_build_lock_left_by_an_interrupted_build_is_removed_and_a_live_one_kept(monkeypatch, tmp_path):
    import os
    import time
    from pathlib import Path

    from torch.utils.cpp_extension import _get_build_directory

    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path))
    lock = Path(_get_build_directory(native.KERNEL_NAME, verbose=False)) / "lock"
    lock.touch()
    native._remove_stale_lock()
    assert lock.exists()  # a build in progress elsewhere: wait for it
    old = time.time() - native.STALE_LOCK_SECONDS - 60
    os.utime(lock, (old, old))
    native._remove_stale_lock()
    assert not lock.exists()
