"""Refinement of a class's cameras, per shape group, and cameras for instances SfM could not place.

With the mean shape of each group fixed, every camera is refined against its keypoints and
its silhouette (:func:`carvi_torch.viewpoints.camera_fit.refine_cameras`); an instance with no
SfM camera (fewer than 2 visible rigid keypoints) gets one by the unseen-image path
(:func:`carvi_torch.viewpoints.camera_fit.estimate_camera`) from its group's mean shape.
Keypoints shown by fewer than ``refine_min_support`` of the instances refined with a shape are
left out of both (:func:`carvi_torch.viewpoints.camera_fit.supported_shape`).

Rows: a class with its mirrored copies has ``2N`` rows (:meth:`ClassCollection.with_mirrors`);
a mixture of shapes assigns every row to a group (:class:`~carvi_torch.viewpoints.mixture.MixtureResult`).

Example:
    >>> rows(torch.arange(5), None).tolist(), rows(torch.arange(5), torch.tensor([1, 3])).tolist()
    ([0, 1, 2, 3, 4], [1, 3])
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import torch

from ..cameras import ScaledOrthographic
from ..collection import ClassCollection
from . import camera_fit
from .choice import CameraChoice, choose_cameras
from .mixture import MixtureResult

if TYPE_CHECKING:
    from ..config import ViewpointConfig

__all__ = ["rows", "group_sfm_cameras", "refine_with_shape", "refine_groups", "choose_per_group", "keypoints_left_out",
           "unseen_keypoints",
           "unseen_per_group", "cameras_from_mean_shape"]


def rows(x, idx):
    """``x`` restricted to the rows ``idx`` (``None``: all of it)."""
    return x if idx is None else x[idx]


def _per_group(mix: MixtureResult, base: ScaledOrthographic, fn: Callable) -> ScaledOrthographic:
    """``base`` with the rows of every shape group replaced by ``fn(g, rows_g)``.

    ``rows_g`` are group ``g``'s rows of the ``2N`` collection, or ``None`` for one group (then
    ``fn(0, None)`` gets every row and returns all of them).
    """
    if mix.k == 1:
        return fn(0, None)
    R, s, t = base.R.clone(), base.s.clone(), base.t.clone()
    for g, (idx, _res) in enumerate(mix.groups):
        c = fn(g, idx)
        R[idx], s[idx], t[idx] = c.R, c.s, c.t
    return ScaledOrthographic(R, s, t)


def _group_rows(mix: MixtureResult, g: int) -> torch.Tensor | None:
    return None if mix.k == 1 else mix.groups[g][0]


def group_sfm_cameras(mix: MixtureResult) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Every group's SfM cameras in the class frame, gathered into the ``2N`` rows; and ``valid (2N,)``."""
    single = mix.single
    if mix.k == 1:
        return single.cameras, single.valid.clone()
    valid = single.valid.clone()
    for idx, res in mix.groups:
        valid[idx] = res.valid
    return _per_group(mix, single.cameras, lambda g, _idx: mix.cameras(g)), valid


def refine_with_shape(shape: torch.Tensor, cams: ScaledOrthographic, both: ClassCollection, dist: torch.Tensor,
                      cfg: ViewpointConfig) -> camera_fit.RefineResult:
    """Silhouette refinement of every camera of ``both`` with the mean shape fixed, as configured
    (without the keypoints fewer than ``refine_min_support`` of ``both`` show)."""
    shape = camera_fit.supported_shape(shape, both.visible, cfg.refine_min_support)
    return camera_fit.refine_cameras(shape, cams, both.keypoints, both.visible, dist,
                                     silhouette_weight=cfg.silhouette_weight, max_iters=cfg.refine_iters,
                                     silhouette_robust=cfg.silhouette_robust or None,
                                     twin_flatness=cfg.refine_twin_flatness)


def refine_groups(mix: MixtureResult, cams_sfm: ScaledOrthographic, both: ClassCollection, dist: torch.Tensor,
                  cfg: ViewpointConfig) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Silhouette refinement of every group with its own mean shape.

    Args:
        mix: the class's shape groups; cams_sfm: ``(2N)`` SfM cameras in the class frame;
        both: the ``2N`` rows; dist: ``(2N, H, W)`` distances to the masks.

    Returns:
        the refined cameras and ``energy (2, 2N)`` (before, after).
    """
    energy = torch.zeros((2, len(both)), dtype=cams_sfm.s.dtype, device=cams_sfm.s.device)

    def refine_group(g, idx):
        rr = refine_with_shape(mix.shape(g), rows(cams_sfm, idx), rows(both, idx), rows(dist, idx), cfg)
        at = slice(None) if idx is None else idx
        energy[0, at], energy[1, at] = rr.energy_before, rr.energy_after
        return rr.cameras

    return _per_group(mix, cams_sfm, refine_group), energy


def choose_per_group(mix: MixtureResult, cams_sfm: ScaledOrthographic, refined: ScaledOrthographic,
                     both: ClassCollection, cfg: ViewpointConfig) -> CameraChoice:
    """:func:`~carvi_torch.viewpoints.choice.choose_cameras` of every row under its group's mean shape (the
    keypoints the refinement used), gathered into the ``2N`` rows (CPU tensors)."""
    parts = []
    for g in range(mix.k):
        idx = _group_rows(mix, g)
        sub = rows(both, idx)
        S = camera_fit.supported_shape(mix.shape(g), sub.visible, cfg.refine_min_support)
        parts.append((idx, choose_cameras(S, rows(cams_sfm, idx), rows(refined, idx), sub.keypoints, sub.visible,
                                          sub.masks)))
    if mix.k == 1:
        return parts[0][1]
    n = len(both)
    out = CameraChoice(torch.zeros(n, dtype=torch.bool), *(torch.zeros(n, dtype=torch.float64) for _ in range(5)))
    for idx, c in parts:
        at = idx.cpu()
        for name in ("suspect", "rms_sfm", "rms_refined", "hull_sfm", "hull_refined", "diagonal"):
            getattr(out, name)[at] = getattr(c, name)
    return out


def keypoints_left_out(mix: MixtureResult, both: ClassCollection, cfg: ViewpointConfig) -> dict[str, list[str]]:
    """Per shape group (``"0"``, ``"1"``...), the names of the keypoints its refinement leaves out;
    groups that keep every keypoint are not listed."""
    out = {}
    for g in range(mix.k):
        S = mix.shape(g)
        kept = camera_fit.supported_shape(S, rows(both, _group_rows(mix, g)).visible, cfg.refine_min_support)
        dropped = (torch.isfinite(S).all(-1) & ~torch.isfinite(kept).all(-1)).nonzero().squeeze(1).tolist()
        if dropped:
            out[str(g)] = [both.meta.keypoint_names[k] for k in dropped]
    return out


def _unseen_shape(shape: torch.Tensor, both: ClassCollection, cfg: ViewpointConfig) -> torch.Tensor:
    """The mean shape the unseen-image path fits to ``both``'s rows (support over all of ``both``)."""
    return camera_fit.supported_shape(shape, both.visible, cfg.refine_min_support)


def cameras_from_mean_shape(shape: torch.Tensor, cams: ScaledOrthographic, idx: torch.Tensor, both: ClassCollection,
                            dist: torch.Tensor, cfg: ViewpointConfig) -> ScaledOrthographic:
    """``cams`` with the cameras of rows ``idx`` replaced by the unseen-image estimate from ``shape``."""
    if idx.numel() == 0:
        return cams
    shape = _unseen_shape(shape, both, cfg)
    est, _energy = camera_fit.estimate_camera(shape, both.keypoints[idx], both.visible[idx], dist[idx],
                                              silhouette_robust=cfg.silhouette_robust or None)
    R, s, t = cams.R.clone(), cams.s.clone(), cams.t.clone()
    R[idx], s[idx], t[idx] = est.R, est.s, est.t
    return ScaledOrthographic(R, s, t)


def unseen_keypoints(mix: MixtureResult, missing: torch.Tensor, both: ClassCollection,
                     cfg: ViewpointConfig) -> torch.Tensor:
    """``(2N,)`` long: for the rows ``missing`` (the unseen-image path), how many of their visible
    keypoints have a row in the mean shape the path fits; -1 elsewhere. 0 means the camera is
    fitted to the silhouette alone."""
    count = torch.full((len(both),), -1, dtype=torch.long, device=missing.device)
    for g in range(mix.k):
        idx = _group_rows(mix, g)
        sub = rows(both, idx)
        S = _unseen_shape(mix.shape(g), sub, cfg)
        seen = (sub.visible & torch.isfinite(sub.keypoints).all(-1) & torch.isfinite(S).all(-1)).sum(-1)
        if idx is None:
            count = torch.where(missing, seen, count)
        else:
            count[idx] = torch.where(missing[idx], seen, count[idx])
    return count


def unseen_per_group(mix: MixtureResult, cams: ScaledOrthographic, missing: torch.Tensor,
                     both: ClassCollection, dist: torch.Tensor, cfg: ViewpointConfig) -> ScaledOrthographic:
    """``cams`` with the rows ``missing (2N,) bool`` estimated from their group's mean shape (unseen-image path)."""
    return _per_group(mix, cams, lambda g, idx: cameras_from_mean_shape(
        mix.shape(g), rows(cams, idx), rows(missing, idx).nonzero().squeeze(1), rows(both, idx), rows(dist, idx),
        cfg))
