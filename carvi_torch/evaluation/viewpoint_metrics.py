"""Viewpoint metrics: compare estimated cameras with ground-truth ones.

Estimated rotations are written in a class's canonical frame
(:mod:`carvi_torch.viewpoints.frame`), ground truth in its own (e.g. PASCAL3D+'s CAD frame:
+z up, front towards -y). :func:`viewpoint_report` compares them twice: ``absolute``, as
written (what a user training on the labels gets), and aligned, after one global rotation
``G`` with ``R_est G ~ R_gt`` (:func:`align_rotations`): the error of the cameras alone,
whatever the frame.
Camera convention (``carvi_torch.cameras``): rows of ``R`` = image x, image y (down),
viewing direction, in the object frame.

Orthographic SfM may also return the mirror image of the true frame (the Necker
ambiguity, when its reflection vote fails): then ``R_est = F R_true Q F`` with
``F = diag(1, 1, -1)`` and no proper ``G`` aligns the sets. :func:`viewpoint_report`
measures both hypotheses and *reports* a mirrored frame; it never silently fixes it.

All angles returned are in degrees.
"""
from __future__ import annotations

import math

import torch

from ..cameras import (align_rotations, azimuth_elevation_roll_from_rotation, check_rotation_pairs,
                       finite_rotation_pairs, geodesic_errors)

__all__ = [
    "align_rotations",
    "geodesic_errors",
    "angle_errors",
    "summarize",
    "viewpoint_report",
    "necker_mirror",
]


def necker_mirror(R: torch.Tensor) -> torch.Tensor:
    """The Necker-mirrored cameras ``F R F``, ``F = diag(1, 1, -1)``: ``(..., 3, 3)`` -> same.

    They see the mirrored object ``F S`` exactly as ``R`` sees ``S``, with depths negated.
    """
    f = torch.tensor([1.0, 1.0, -1.0], dtype=R.dtype, device=R.device)
    return f[:, None] * R * f[None, :]


def _wrap_deg(a: torch.Tensor) -> torch.Tensor:
    """Absolute angle difference wrapped to ``[0, 180]`` degrees, from radians."""
    return torch.rad2deg(torch.remainder(a + math.pi, 2 * math.pi) - math.pi).abs()


def angle_errors(R_est: torch.Tensor, R_gt: torch.Tensor, G: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Azimuth, elevation and roll errors (degrees, wrapped) of ``R_est G`` vs ``R_gt``.

    Angles follow PASCAL3D+ (``cameras.azimuth_elevation_roll_from_rotation``; the
    ground-truth object frame has +z up and its front towards -y).

    Returns:
        ``{"azimuth": (N,), "elevation": (N,), "roll": (N,)}``, each in ``[0, 180]``.
    """
    check_rotation_pairs(R_est, R_gt)
    Re = R_est if G is None else R_est @ G.to(R_est)
    a1, e1, r1 = azimuth_elevation_roll_from_rotation(Re)
    a2, e2, r2 = azimuth_elevation_roll_from_rotation(R_gt.to(Re))
    return {"azimuth": _wrap_deg(a1 - a2), "elevation": _wrap_deg(e1 - e2), "roll": _wrap_deg(r1 - r2)}


def summarize(errors: torch.Tensor, threshold: float = 30.0) -> dict:
    """Median, mean and accuracy of angular errors (degrees); NaNs are left out.

    The median of an even count is the mean of the two middle values (as numpy and
    MATLAB's ``median``, which PASCAL3D+'s MedErr uses), not ``torch.median``'s lower one.

    Returns:
        ``{"n": int, "median": float, "mean": float, "acc_at_30": float}`` where
        ``acc_at_30`` is the fraction of errors below ``threshold`` degrees
        (PASCAL3D+'s ``Acc_pi/6`` with the default). Empty input gives NaNs and ``n = 0``.

    Example:
        >>> summarize(torch.tensor([1.0, 2.0, 40.0]))["acc_at_30"]
        0.6666666865348816
    """
    e = torch.as_tensor(errors).flatten()
    e = e[torch.isfinite(e)]
    if e.numel() == 0:
        return {"n": 0, "median": float("nan"), "mean": float("nan"), "acc_at_30": float("nan")}
    return {
        "n": int(e.numel()),
        "median": float(torch.quantile(e.double(), 0.5)),
        "mean": float(e.mean()),
        "acc_at_30": float((e < threshold).float().mean()),
    }


def viewpoint_report(
    R_est: torch.Tensor,
    R_gt: torch.Tensor,
    *,
    valid: torch.Tensor | None = None,
    robust: bool = False,
    alignment: torch.Tensor | None = None,
) -> dict:
    """Everything about estimated vs ground-truth viewpoints, JSON-ready.

    Aligns the frames (:func:`align_rotations`, or the given ``alignment``), then reports geodesic, azimuth,
    elevation and roll error summaries. It also aligns the Necker-mirrored cameras
    (:func:`necker_mirror`) and sets ``"mirrored": True`` when they fit the ground
    truth better (median geodesic error): the estimated object frame is then the
    mirror image of the true one. The reported errors stay those of the cameras as
    given.

    Args:
        R_est, R_gt: ``(N, 3, 3)``.
        valid: ``(N,)`` bool, pairs to use (default: all finite).
        robust: robust alignment.
        alignment: ``(3, 3)`` a global rotation ``G`` (``R_est G ~ R_gt``) fitted elsewhere,
            e.g. on other instances of the same SfM frame (cameras of unseen images
            evaluated without fitting ``G`` to their own ground truth). ``None``: fit it
            here. The mirrored hypothesis is always fitted here.

    Returns:
        ``{"n", "alignment" (3x3 list), "geodesic", "azimuth", "elevation", "roll"
        (each a :func:`summarize` dict, after the alignment), "absolute" (the same four
        without any fitted rotation), "mirrored" (bool), "mirrored_geodesic" (summary of
        the mirrored hypothesis), "per_instance_geodesic" (list, NaN for unused pairs)}``.
    """
    check_rotation_pairs(R_est, R_gt)
    use = finite_rotation_pairs(R_est, R_gt)
    if valid is not None:
        v = torch.as_tensor(valid, device=R_est.device).bool()
        if v.shape != use.shape:
            raise ValueError(f"valid must be ({use.shape[0]},), got {tuple(v.shape)}")
        use = use & v
    if not bool(use.any()):
        raise ValueError("viewpoint_report: no valid pair of finite rotations")
    Re, Rg = R_est[use], R_gt[use]
    if alignment is None:
        G = align_rotations(Re, Rg, robust=robust)
    else:
        G = torch.as_tensor(alignment).to(Re)
        if G.shape != (3, 3) or not bool(torch.isfinite(G).all()):
            raise ValueError(f"alignment must be a finite (3, 3) rotation, got {tuple(G.shape)}")
    geo = geodesic_errors(Re, Rg, G)
    ang = angle_errors(Re, Rg, G)
    ang_abs = angle_errors(Re, Rg)
    Rm = necker_mirror(Re)
    Gm = align_rotations(Rm, Rg, robust=robust)
    geo_m = geodesic_errors(Rm, Rg, Gm)
    per = torch.full(use.shape, float("nan"), dtype=geo.dtype, device=geo.device)
    per[use] = geo
    report = {
        "n": int(use.sum()),
        "alignment": G.double().cpu().tolist(),
        "geodesic": summarize(geo),
        "azimuth": summarize(ang["azimuth"]),
        "elevation": summarize(ang["elevation"]),
        "roll": summarize(ang["roll"]),
        "absolute": {"geodesic": summarize(geodesic_errors(Re, Rg)),
                     **{k: summarize(ang_abs[k]) for k in ("azimuth", "elevation", "roll")}},
        "mirrored": bool(geo_m.median() < geo.median()),
        "mirrored_geodesic": summarize(geo_m),
        "per_instance_geodesic": per.double().cpu().tolist(),
    }
    return report
