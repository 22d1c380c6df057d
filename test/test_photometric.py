"""The colour tracking compares (slam.photometric): blind to smooth and global gains, keeps the texture."""
import torch

from gausem_core.data.sensor import vignetting
from gausem_core.geometry import PinholeCamera
from gausem_core.slam.photometric import local_contrast

CAMERA = PinholeCamera(80.0, 80.0, 40.0, 30.0, 80, 60)


def texture(seed=0):
    """(60, 80, 3) colours in [0.2, 0.8] with texture at a few pixels' scale."""
    coarse = torch.rand(1, 3, 15, 20, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    fine = torch.nn.functional.interpolate(coarse, size=(60, 80), mode="bilinear", align_corners=False)
    return (0.2 + 0.6 * fine)[0].permute(1, 2, 0)


def test_local_contrast_cancels_exposure_white_balance_and_vignetting():
    image = texture()
    gain = 1.4 * torch.tensor([0.8, 1.0, 1.2], dtype=torch.float64)  # exposure times white balance
    falloff = torch.from_numpy(vignetting(CAMERA, 0.75))[..., None]  # 75 % in the corners
    seen = image * falloff * gain
    raw_change = (seen - image).abs().mean()
    change = (local_contrast(seen, 0.1) - local_contrast(image, 0.1)).abs().mean()
    assert change < 0.1 * raw_change, (float(change), float(raw_change))


def test_local_contrast_keeps_the_texture():
    image = texture()
    out = local_contrast(image, 0.1)
    # the normalised image still tells the pixels apart: it follows the texture closely
    centred = [(x - x.mean()).reshape(-1) for x in (image, out)]
    correlation = centred[0] @ centred[1] / (centred[0].norm() * centred[1].norm())
    assert correlation > 0.9


def test_local_contrast_uses_the_masked_pixels_only_and_zero_width_is_raw():
    image = texture()
    mask = torch.zeros(60, 80, dtype=torch.bool)
    mask[:, :40] = True
    other = image.clone()
    other[:, 40:] = 0.0  # what a render has outside its silhouette
    assert torch.allclose(local_contrast(image, 0.1, mask)[mask], local_contrast(other, 0.1, mask)[mask])
    assert local_contrast(image, 0.0) is image
