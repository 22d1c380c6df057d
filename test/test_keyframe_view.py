"""Frame-to-keyframe fill: the newest keyframe's own images where the rendered model view has no silhouette."""
import torch

from gausem_core.geometry import PinholeCamera, se3_exp
from gausem_core.slam.direct_alignment import ModelView
from gausem_core.slam.keyframe_view import KeyframeView, fill_from_keyframe
from gausem_core.slam.observation import Observation

CAMERA = PinholeCamera(40.0, 40.0, 16.0, 12.0, 32, 24)


def keyframe(depth: torch.Tensor) -> Observation:
    rgb = torch.rand(24, 32, 3)
    return Observation(rgb, depth, rgb.flip(-1), torch.zeros(24, 32, dtype=torch.long), CAMERA)


def empty_view(rendered: torch.Tensor | None = None) -> ModelView:
    """A rendered view with a silhouette only where ``rendered`` (H, W) is true: depth 5 m, grey there."""
    mask = torch.zeros(24, 32, dtype=torch.bool) if rendered is None else rendered
    return ModelView(torch.full((24, 32, 3), 0.5), torch.full((24, 32, 3), 0.5), torch.full((24, 32), 5.0), mask,
                     CAMERA)


def test_at_the_keyframes_own_pose_its_valid_pixels_fill_the_view_as_they_are():
    depth = torch.full((24, 32), 2.0)
    depth[:, :4] = 0  # no depth: not filled
    obs = keyframe(depth)
    rendered = torch.zeros(24, 32, dtype=torch.bool)
    rendered[10:14, 10:20] = True  # the map covers these: they keep their rendered values
    view = fill_from_keyframe(empty_view(rendered), torch.eye(4), KeyframeView.of(obs, torch.eye(4)))
    expected = (depth > 0) & ~rendered
    assert torch.equal(view.mask, expected | rendered)
    assert torch.equal(view.depth[expected], depth[expected]) and torch.equal(view.color[expected], obs.rgb[expected])
    assert torch.equal(view.semantic[expected], obs.semantic[expected])
    assert (view.depth[rendered] == 5.0).all() and (view.color[rendered] == 0.5).all()


def test_a_moved_keyframe_lands_where_its_points_project_and_the_nearest_wins():
    depth = torch.full((24, 32), 2.0)
    depth[:, :16] = 1.0  # the left half nearer
    obs = keyframe(depth)
    shift = se3_exp(torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0, 0.0]))  # the keyframe 10 cm to the right of the view
    view = fill_from_keyframe(empty_view(), torch.eye(4), KeyframeView.of(obs, shift))
    # a point at depth d moves 0.1 * 40 / d pixels: 4 px at 1 m, 2 px at 2 m; the view's left 4 columns see nothing,
    # and on columns 18-19 the near half's edge hides the far half's first two columns
    assert not view.mask[:, :4].any() and view.mask[:, 4:].all()
    assert (view.depth[:, 4:20] == 1.0).all() and torch.equal(view.color[:, 4:20], obs.rgb[:, :16])
    assert (view.depth[:, 20:] == 2.0).all() and torch.equal(view.color[:, 20:], obs.rgb[:, 18:30])
