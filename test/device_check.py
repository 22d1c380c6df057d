"""Checks that tensors are on the GPU, for the cuda-marked tests."""
import dataclasses

import torch

from gausem_core.slam.system import FrameResult, GauSemSLAM

CUDA = torch.device("cuda")


def tensors(obj, path: str = ""):
    """(path, tensor) of every tensor in ``obj`` and in the dataclasses, lists, tuples and dicts it holds."""
    if isinstance(obj, torch.Tensor):
        yield path, obj
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        for f in dataclasses.fields(obj):
            yield from tensors(getattr(obj, f.name), f"{path}.{f.name}")
    elif isinstance(obj, (list, tuple)):
        for i, item in enumerate(obj):
            yield from tensors(item, f"{path}[{i}]")
    elif isinstance(obj, dict):
        for key, item in obj.items():
            yield from tensors(item, f"{path}[{key!r}]")


def assert_on_cuda(**named) -> None:
    found = [(name + path, t) for name, obj in named.items() for path, t in tensors(obj)]
    assert found, "no tensor to check"
    elsewhere = [f"{path} on {t.device}" for path, t in found if t.device.type != "cuda"]
    assert not elsewhere, elsewhere


def frame_results(results: list[FrameResult]) -> list[dict]:
    """What a frame result holds besides its events (whose poses are float64 CPU copies by contract,
    ``slam.events``), for :func:`assert_on_cuda`."""
    return [{f.name: getattr(r, f.name) for f in dataclasses.fields(r) if f.name != "events"} for r in results]


def assert_events_on_cpu(results: list[FrameResult]) -> None:
    """The events' poses and anchors are float64 on the CPU, as ``slam.events`` promises its readers."""
    found = [(path, t) for i, r in enumerate(results) for path, t in tensors(r.events, f"results[{i}].events")]
    assert found, "no event tensor to check"
    assert all(t.device.type == "cpu" and t.dtype == torch.float64 for _, t in found), found


def system_results(slam: GauSemSLAM) -> dict:
    """What the system hands back: poses, anchors, the active submap's Gaussians and observations, every submap's
    Gaussians and keyframe observations read back onto the GPU, the global map."""
    return {"trajectory": [pose for _, pose in slam.trajectory()],
            "anchors": [s.anchor for s in slam.submaps],
            "keyframe_poses": [kf.cam_to_world for s in slam.submaps for kf in s.keyframes],
            "active_cloud": slam.active.cloud,
            "active_observations": [kf.obs for kf in slam.active.keyframes],
            "loaded_clouds": [s.load_cloud(CUDA) for s in slam.submaps],
            "loaded_observations": [s.observation(kf, CUDA) for s in slam.submaps for kf in s.keyframes],
            "global_cloud": slam.global_cloud()}
