"""Two-stage global map refinement after the last frame (paper §III-C, last paragraph).

Stage 1, per submap: Gaussians and (non-fixed) keyframe poses are optimised jointly with
L_refine = L_map + lambda_feat * ||F(S_pix) - F(S)||^2, the mapping loss plus the squared distance between the dense
semantic features of the input segmentation and of the rendered semantics, visiting every keyframe
``refinement.iterations_per_keyframe`` times (in a shuffled order per pass). L_map's depth weight is the refinement's
own (``refinement.w_depth``), and the learning rates of the Gaussian centres and of the keyframe poses can decay
exponentially over the passes (to ``refinement.final_lr_means_fraction`` and ``refinement.final_lr_pose_fraction``,
as 3DGS does for the centres), so map and poses settle instead of jittering between views that disagree (motion blur,
rolling shutter on real sequences).

Stage 2, alignment to the global map: each submap's anchor is refined by registering the submap (its keyframe views,
rendered in the submap frame) to the union of all OTHER submaps in world coordinates, with the Gauss-Newton fine step
of SGR (the submap's own Gaussians would only pull it back to where it is); an accepted result replaces the anchor.
The fused global map is then the union of the submaps moved by their anchors, x = T_a x_i
(``GauSemSLAM.global_cloud``).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from gausem_core.config import RefinementConfig, RegistrationConfig
from gausem_core.gaussians import GaussianCloud
from gausem_core.geometry import invert_pose, se3_exp
from gausem_core.render import render
from gausem_core.semantics.descriptors import DescriptorExtractor
from gausem_core.slam.adam import AdamSteps, ParameterGroup
from gausem_core.slam.losses import mapping_loss
from gausem_core.slam.mapper import Keyframe, Mapper, gaussian_groups
from gausem_core.slam.observation import Observation
from gausem_core.slam.registration import fine_registration, is_acceptable


@dataclass(frozen=True)
class RefinementReport:
    """Mean L_refine of each submap's first and last pass (stage 1) and which anchors stage 2 moved."""

    first_pass_loss: dict[int, float]
    last_pass_loss: dict[int, float]
    aligned: dict[int, bool]


def refine_submap(cloud: GaussianCloud, keyframes: list[Keyframe], observations: list[Observation], mapper: Mapper,
                  passes: int, features: DescriptorExtractor | None, lambda_feat: float,
                  backend: str = "auto", w_depth: float | None = None,
                  final_lr_means_fraction: float = 1.0,
                  final_lr_pose_fraction: float = 1.0) -> tuple[GaussianCloud, list[float]]:
    """Stage 1 on one submap: ``passes`` shuffled passes over the keyframes (with their ``observations``)
    minimising L_refine.

    Uses the mapper's learning rates and loss weights, except the depth weight ``w_depth`` when given; the centres'
    learning rate decays exponentially to ``final_lr_means_fraction`` of the mapper's by the last step, the poses' to
    ``final_lr_pose_fraction``. Non-fixed keyframe poses are updated in place. Returns the refined (pruned) cloud,
    colours unclamped, and the mean loss of every pass.
    """
    cfg = mapper.cfg
    w_depth = cfg.w_depth if w_depth is None else w_depth
    params = cloud.clone().requires_grad_(True)
    groups = gaussian_groups(params, cfg, {"means": final_lr_means_fraction})
    twists = [None if kf.fixed else torch.zeros(6, dtype=params.dtype, device=params.device, requires_grad=True)
              for kf in keyframes]
    movable = [t for t in twists if t is not None]
    if movable:
        groups.append(ParameterGroup(movable, cfg.lr_pose, final_lr_pose_fraction))
    adam = AdamSteps(groups, horizon=max(passes * len(keyframes) - 1, 1))  # the last step at the final rates
    with torch.no_grad():
        targets = [features.dense_features(obs.semantic) if features is not None else None for obs in observations]
    pass_losses = []
    for _ in range(passes):
        losses = []
        for i in torch.randperm(len(keyframes), generator=mapper.generator).tolist():
            obs = observations[i]
            w2c = invert_pose(keyframes[i].cam_to_world.to(params.device, params.dtype))
            if twists[i] is not None:
                w2c = se3_exp(twists[i]) @ w2c
            out = render(params, w2c, obs.camera, backend=backend)
            loss = mapping_loss(out, obs, cfg.w_color, w_depth, cfg.w_semantic, cfg.ssim_lambda)
            if targets[i] is not None:
                loss = loss + lambda_feat * (features.dense_features(out.semantic) - targets[i]).pow(2).sum(-1).mean()
            adam.step(loss)
            losses.append(loss.detach())
        pass_losses.append(sum(torch.stack(losses).tolist()) / max(len(keyframes), 1) if losses else 0.0)
    with torch.no_grad():
        for kf, twist in zip(keyframes, twists):
            if twist is not None:
                pose = kf.cam_to_world
                kf.cam_to_world = invert_pose(se3_exp(twist) @ invert_pose(pose.to(params.device, params.dtype))).to(
                    pose.device, pose.dtype)
        # colours are left as optimised: values beyond [0, 1] make up for partial opacity where Gaussians overlap
        # (7 % above 1 and 6 % below 0 on tum_fr1_rpy), clamping them cost 0.7 dB there; semantics are classified
        params.semantics.clamp_(0, 1)
    return mapper.strategy.prune(params.detach()), pass_losses


def align_to_global(submap, others: Sequence, cfg: RegistrationConfig, features: DescriptorExtractor | None,
                    backend: str = "auto", device: torch.device | str = "cpu") -> bool:
    """Stage 2 on one submap: register it to the other submaps (world frame) from its anchor; move the anchor when
    the registration is accepted. Returns whether it moved."""
    cloud = submap.load_cloud(device)
    if not others or len(cloud) == 0:
        return False
    world = GaussianCloud.cat([s.load_cloud(device).transformed(s.anchor.to(device)) for s in others])
    count = min(cfg.views, len(submap.keyframes))
    picks = torch.linspace(0, len(submap.keyframes) - 1, count).round().long().unique()
    poses = torch.stack([submap.keyframes[i].cam_to_world.detach().double().cpu() for i in picks.tolist()])
    fine = fine_registration(cloud, world, poses, submap.keyframes[0].obs.camera,
                             submap.anchor.detach().double().cpu(), cfg, features, backend)
    if not is_acceptable(fine, cfg):
        return False
    submap.anchor = fine.transform.to(submap.anchor.dtype).to(submap.anchor.device)
    return True


def global_refinement(submaps: Sequence, mapper: Mapper, cfg: RefinementConfig, registration: RegistrationConfig,
                      features: DescriptorExtractor | None, backend: str = "auto",
                      device: torch.device | str = "cpu") -> RefinementReport:
    """Both stages over all submaps (edited in place; offloaded ones are loaded onto ``device`` and written back);
    ``registration``: loop closure's, whose ``lambda_feat`` weighs stage 1's feature term and which stage 2 registers
    with. The first submap is the world's reference: stage 2 aligns the others and leaves its anchor alone."""
    first, last, aligned = {}, {}, {}
    for submap in submaps:
        if not submap.keyframes or cfg.iterations_per_keyframe <= 0:
            continue
        observations = [submap.observation(kf, device) for kf in submap.keyframes]
        submap.cloud, losses = refine_submap(submap.take_cloud(device), submap.keyframes, observations, mapper,
                                             cfg.iterations_per_keyframe, features, registration.lambda_feat,
                                             backend, cfg.w_depth, cfg.final_lr_means_fraction,
                                             cfg.final_lr_pose_fraction)
        first[submap.submap_id], last[submap.submap_id] = losses[0], losses[-1]
    for submap in submaps[1:]:
        if submap.keyframes:
            others = [s for s in submaps if s is not submap]
            aligned[submap.submap_id] = align_to_global(submap, others, registration, features, backend, device)
    return RefinementReport(first, last, aligned)
