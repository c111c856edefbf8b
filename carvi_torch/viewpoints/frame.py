"""The canonical object frame of a class: where viewpoint labels and class-frame shapes are written.

SfM finds a class's mean shape and cameras up to one rotation (and scale) of the object frame. This
step fixes that rotation, so that ``R``, azimuth, elevation and roll mean the same for every class
and every run:

* ``template``: the similarity ``X' = c Q X + tau`` (``Q`` a proper rotation: a reflection is never
  accepted) that maps the SfM mean shape onto a template of 3-D keypoints (weighted Umeyama, with
  Cauchy reweighting of keypoints that disagree; shape groups share one rotation). A COCO category
  may carry its own template (``keypoints_3d``); the 12 PASCAL3D+ classes have shipped ones
  (``templates.json``, built from the CAD models by :func:`build_templates`), in the PASCAL3D+ CAD
  frame (+z up, front towards -y), so that azimuth, elevation and roll follow PASCAL3D+'s
  definitions. Keypoints are matched by name,
  Berkeley VOC names through an alias table (``L_WingTip`` is PASCAL3D+'s ``right_wing``).
* ``symmetry+up`` (no template, or one the data disagree with): x along the normal of the class's
  left-right symmetry plane, z (up) in that plane and as perpendicular as it can be to both the
  cameras' image x axes (photographs are taken with a level camera: little roll) and their viewing
  directions (and from near the ground plane: little elevation), pointing like the photographs' image
  up, y = z x x; the front is the -y side when front- and back-named keypoints tell it (else it is
  ambiguous, and said so).
* ``sfm``: the SfM frame itself (no flip pairs to find a symmetry plane).

The frame changes only what is written (cameras, angles, mean shapes, class-frame transforms);
carving and selection work in any frame.

Example:
    >>> S = torch.tensor([[1.0, 0, 0], [0, 2, 0], [0, 0, 3], [1, 1, 1]])
    >>> Q = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    >>> fit = fit_similarity(S, 2 * S @ Q.T + 5)
    >>> torch.allclose(fit.Q, Q.double(), atol=1e-6), round(fit.c, 6), round(fit.residual, 6)
    (True, 2.0, 0.0)
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import torch

from ..cameras import ScaledOrthographic
from .sfm import keypoint_end

__all__ = ["FrameKind", "FrameChoice", "FrameFit", "CanonicalFrame", "fit_similarity", "symmetry_up_frame",
           "load_templates", "template_points", "build_templates", "canonical_frame", "TEMPLATES_PATH",
           "MAX_TEMPLATE_RESIDUAL", "VOC_ALIASES"]

#: What a class's canonical frame was found from.
FrameKind = Literal["template", "symmetry+up", "sfm", "ground_truth"]
#: What a run asks for: ``best`` (a template when one fits, else symmetry+up, else sfm) or one of them.
FrameChoice = Literal["best", "template", "symmetry+up", "sfm"]
#: The shipped templates of the PASCAL3D+ classes.
TEMPLATES_PATH = Path(__file__).with_name("templates.json")
#: A template is refused when its robust residual (median distance over the template's RMS radius)
#: exceeds this: the data disagree with it.
MAX_TEMPLATE_RESIDUAL = 0.25
#: Fewest keypoints a template fit needs.
MIN_MATCHED = 4


@dataclass
class FrameFit:
    """``X' = c Q X + tau``: SfM object-frame points ``X`` into the canonical frame (``Q`` proper, ``(3, 3)``
    float64). ``residual``: the fit's robust residual (template fits), ``matched``: keypoints used."""

    Q: torch.Tensor
    c: float = 1.0
    tau: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    residual: float | None = None
    matched: int = 0


def _identity() -> FrameFit:
    return FrameFit(torch.eye(3, dtype=torch.float64))


def fit_similarity(S: torch.Tensor, T: torch.Tensor, iters: int = 10, Q: torch.Tensor | None = None) -> FrameFit:
    """The proper similarity mapping the rows of ``S (K, 3)`` onto those of ``T (K, 3)`` (rows with a
    non-finite entry in either are ignored), by weighted Umeyama with Cauchy reweighting; with ``Q``
    given, only its scale and translation.

    Returns a :class:`FrameFit` whose ``residual`` is the robust median distance after the fit, each
    template axis rescaled on its own (proportions are not a misfit), over the RMS radius of the
    matched template points.
    """
    ok = torch.isfinite(S).all(-1) & torch.isfinite(T).all(-1)
    if int(ok.sum()) < 3:
        raise ValueError(f"a similarity needs 3 shared points, got {int(ok.sum())}")
    A, B = S[ok].double(), T[ok].double()
    w = torch.ones(len(A), dtype=torch.float64)
    fixed = Q = None if Q is None else Q.double()
    for _ in range(iters):
        ma, mb = (w[:, None] * A).sum(0) / w.sum(), (w[:, None] * B).sum(0) / w.sum()
        Ac, Bc = A - ma, B - mb
        if fixed is None:
            U, D, Vh = torch.linalg.svd((w[:, None] * Bc).T @ Ac)
            E = torch.diag(torch.tensor([1.0, 1.0, float(torch.sign(torch.det(U @ Vh))) or 1.0], dtype=torch.float64))
            Q = U @ E @ Vh
        c = float((w[:, None] * Bc * (Ac @ Q.T)).sum() / (w * (Ac ** 2).sum(-1)).sum().clamp(min=1e-300))
        tau = mb - c * Q @ ma
        r = (c * A @ Q.T + tau - B).norm(dim=-1)
        scale = float(1.4826 * r.median()) + 1e-12
        w = 1.0 / (1.0 + (r / (2.0 * scale)) ** 2)
    radius = float(((B - B.mean(0)) ** 2).sum(-1).mean().sqrt()) + 1e-300
    Y = c * A @ Q.T + tau  # then each template axis scaled on its own: proportions are not a misfit
    Yc, Bc = Y - (w[:, None] * Y).sum(0) / w.sum(), B - (w[:, None] * B).sum(0) / w.sum()
    a = ((w[:, None] * Yc * Bc).sum(0) / (w[:, None] * Yc ** 2).sum(0).clamp(min=1e-300)).clamp(min=0)  # no flips
    r = (Yc * a - Bc).norm(dim=-1)
    return FrameFit(Q, c, tau, float(r.median()) / radius, int(ok.sum()))


# --------------------------------------------------------------------------- templates


def load_templates(path: str | Path = TEMPLATES_PATH) -> dict:
    """The shipped templates: ``{"classes": {name: {"keypoints": {kp: [x, y, z]}, ...}}, "aliases": ...}``."""
    return json.loads(Path(path).read_text())


def _lookup(name: str, points: dict, aliases: dict) -> list | None:
    lower = {k.lower(): v for k, v in points.items()}
    alias = {k.lower(): v.lower() for k, v in aliases.items()}.get(name.lower())
    return lower.get(name.lower()) or (lower.get(alias) if alias else None)


def template_points(class_name: str, keypoint_names: list, templates: dict,
                    own: list | None = None) -> tuple[torch.Tensor, str] | None:
    """``(T (K, 3) float64, source)``: the template point of each of a class's keypoints (NaN rows: not
    in the template), from the category's own ``keypoints_3d`` (``own``) or the shipped template of
    the class name; ``None`` when fewer than :data:`MIN_MATCHED` keypoints are known."""
    K = len(keypoint_names)
    T = torch.full((K, 3), math.nan, dtype=torch.float64)
    if own is not None:
        for k, p in enumerate(own[:K]):
            if p is not None and len(p) == 3 and all(isinstance(v, (int, float)) for v in p):
                T[k] = torch.tensor(p, dtype=torch.float64)
        source = "category keypoints_3d"
    else:
        entry = templates.get("classes", {}).get(class_name.lower())
        if entry is None:
            return None
        aliases = templates.get("aliases", {}).get(class_name.lower(), {})
        for k, name in enumerate(keypoint_names):
            p = _lookup(name, entry["keypoints"], aliases)
            if p is not None:
                T[k] = torch.tensor(p, dtype=torch.float64)
        source = f"shipped template '{class_name.lower()}'"
    return (T, source) if int(torch.isfinite(T).all(-1).sum()) >= MIN_MATCHED else None


def build_templates(models) -> dict:
    """Templates from CAD models with 3-D keypoints (``.category``, ``.vertices``, ``.keypoint_names``,
    ``.keypoints``): each model centred on its bounding box and scaled to a unit diagonal, each keypoint
    averaged over the models that have it."""
    sums: dict = {}
    for m in models:
        v = torch.as_tensor(m.vertices, dtype=torch.float64)
        lo, hi = v.amin(0), v.amax(0)
        kp = (torch.as_tensor(m.keypoints, dtype=torch.float64) - (lo + hi) / 2) / float((hi - lo).norm())
        cls = sums.setdefault(m.category, {"models": 0, "keypoints": {}})
        cls["models"] += 1
        for name, p in zip(m.keypoint_names, kp):
            acc = cls["keypoints"].setdefault(str(name), [torch.zeros(3, dtype=torch.float64), 0])
            acc[0] += p
            acc[1] += 1
    return {c: {"models": e["models"],
                "keypoints": {n: [round(float(x), 6) for x in (s / k)] for n, (s, k) in sorted(e["keypoints"].items())},
                "counts": {n: k for n, (s, k) in sorted(e["keypoints"].items())}}
            for c, e in sorted(sums.items())}


# --------------------------------------------------------------------------- the automatic frame


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm().clamp(min=1e-300)


def symmetry_up_frame(reflection: torch.Tensor, R: torch.Tensor, shape: torch.Tensor,
                      keypoint_names: list | None) -> tuple[FrameFit, dict]:
    """The automatic frame from the symmetry plane and the cameras (see the module docstring).

    Args:
        reflection: ``(3, 3)`` reflection through the class's left-right symmetry plane (``I - 2 n n^T``).
        R: ``(N, 3, 3)`` the class's cameras (rows: image x, image y down, viewing direction).
        shape: ``(K, 3)`` mean shape (NaN rows allowed); keypoint_names: its ``K`` names, for the front.

    Returns:
        the fit (``c = 1``, ``tau = 0``) and what it measured: ``elevation_rms_deg`` and ``roll_rms_deg``
        (RMS elevation and roll of the cameras in the frame found), ``up_margin`` (the second smallest
        over the smallest eigenvalue: near 1, up is ambiguous), ``front`` (``"names"`` or ``"ambiguous"``).
    """
    P = reflection.double()
    evals, evecs = torch.linalg.eigh(P)
    n = evecs[:, 0]  # eigenvalue -1: the plane's normal
    Rd = R.double()
    rows = torch.cat([Rd[:, 0, :], Rd[:, 2, :]])  # image x (level camera) and viewing direction (near level)
    proj = torch.eye(3, dtype=torch.float64) - torch.outer(n, n)
    C = proj @ (rows.T @ rows / len(rows)) @ proj
    w, vecs = torch.linalg.eigh(C + 10.0 * torch.outer(n, n))  # n pushed to the top: not a candidate
    up = vecs[:, 0]
    if float(up @ (-Rd[:, 1, :]).mean(0)) < 0:
        up = -up
    front = torch.linalg.cross(up, n)  # any in-plane axis perpendicular to up; its sign from the names
    sign, how = _front_sign(shape, front, keypoint_names)
    y = -_unit(sign * front)
    z = _unit(up)
    Q = torch.stack([torch.linalg.cross(y, z), y, z])
    info = {"elevation_rms_deg": _rms_angle(Rd[:, 2, :] @ z), "roll_rms_deg": _rms_angle(Rd[:, 0, :] @ z),
            "up_margin": round(float(w[1] / w[0].clamp(min=1e-12)), 3), "front": how}
    return FrameFit(Q), info


def _rms_angle(sines: torch.Tensor) -> float:
    """RMS of ``asin`` of the entries, in degrees."""
    return round(math.degrees(float(torch.asin(sines.clamp(-1, 1)).pow(2).mean().sqrt())), 3)


def _front_sign(shape: torch.Tensor, axis: torch.Tensor, names: list | None) -> tuple[float, str]:
    """+1 when the front-named keypoints lie along ``axis`` from the back-named ones, -1 against it."""
    if names is None:
        return 1.0, "ambiguous"
    ok = torch.isfinite(shape).all(-1)
    ends = [keypoint_end(str(nm)) for nm in names]
    fr = [k for k, e in enumerate(ends) if e == "front" and bool(ok[k])]
    bk = [k for k, e in enumerate(ends) if e == "back" and bool(ok[k])]
    if not fr or not bk:
        return 1.0, "ambiguous"
    proj = shape.double() @ axis.double()  # medians: one badly placed keypoint does not turn the frame
    d = float(proj[fr].median() - proj[bk].median())
    return (1.0 if d >= 0 else -1.0), "names"


# --------------------------------------------------------------------------- the class's frame


@dataclass
class CanonicalFrame:
    """A class's canonical frame: one :class:`FrameFit` per shape group (one rotation for all; a scale and offset each).

    Attributes:
        kind: :data:`FrameKind`; fits: per shape group; info: what ``cameras.json`` and ``summary.json``
        say of it (kind, residuals, template source, ambiguities, why a template was refused).
    """

    kind: FrameKind
    fits: list
    info: dict = field(default_factory=dict)

    def _fit(self, g: int) -> FrameFit:
        return self.fits[min(g, len(self.fits) - 1)]

    def cameras(self, cams: ScaledOrthographic, groups: torch.Tensor | None = None) -> ScaledOrthographic:
        """Cameras ``(N)`` of the SfM frame in the canonical frame (``groups (N,)``: each row's shape group):
        ``R' = R Q^T``, ``s' = s / c``, ``t' = t - s' R'[:2] tau``."""
        dt = cams.R.dtype
        g = torch.zeros(len(cams), dtype=torch.long) if groups is None else groups.long().cpu()
        fits = [self._fit(i) for i in range(int(g.max()) + 1 if len(g) else 1)]
        Q = torch.stack([f.Q for f in fits])[g].to(cams.R)
        c = torch.tensor([f.c for f in fits], dtype=dt)[g].to(cams.s)
        tau = torch.stack([f.tau for f in fits])[g].to(cams.R)
        R = cams.R @ Q.transpose(1, 2)
        s = cams.s / c
        t = cams.t - s[:, None] * (R[:, :2, :] @ tau[:, :, None])[..., 0]
        return ScaledOrthographic(R, s, t)

    def points(self, S: torch.Tensor, g: int = 0) -> torch.Tensor:
        """``(K, 3)`` SfM-frame points of group ``g`` in the canonical frame."""
        f = self._fit(g)
        return f.c * S.double() @ f.Q.T + f.tau

    def directions(self, A: torch.Tensor, g: int = 0) -> torch.Tensor:
        """``(M, 3)`` SfM-frame directions (rows) in the canonical frame."""
        return A.double() @ self._fit(g).Q.T

    def reflection(self, P: torch.Tensor, g: int = 0) -> torch.Tensor:
        """A ``(3, 3)`` reflection of the SfM frame in the canonical frame (``Q P Q^T``)."""
        Q = self._fit(g).Q
        return Q @ P.double() @ Q.T


def _normalised(S: torch.Tensor, T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The rows both know, each set centred and scaled to a unit RMS radius."""
    ok = torch.isfinite(S).all(-1) & torch.isfinite(T).all(-1)
    A, B = S[ok].double(), T[ok].double()
    A, B = A - A.mean(0), B - B.mean(0)
    return A / A.pow(2).sum(-1).mean().sqrt().clamp(min=1e-300), B / B.pow(2).sum(-1).mean().sqrt().clamp(min=1e-300)


def _template_frame(group_shapes: list, T: torch.Tensor, source: str) -> tuple[CanonicalFrame | None, str]:
    """Every shape group aligned to the template by one rotation (the groups share the SfM class frame:
    one rotation keeps their cameras consistent), each with its own scale and offset; or why not (a
    group the template does not fit)."""
    Q = None
    if len(group_shapes) > 1:
        pairs = [_normalised(S, T) for S in group_shapes]
        try:
            Q = fit_similarity(torch.cat([a for a, _ in pairs]), torch.cat([b for _, b in pairs])).Q
        except ValueError as e:
            return None, str(e)
    fits = []
    for g, S in enumerate(group_shapes):
        try:
            fit = fit_similarity(S, T, Q=Q)
        except ValueError as e:
            return None, f"group {g}: {e}"
        if fit.residual > MAX_TEMPLATE_RESIDUAL:
            return None, (f"the {source} fits the mean shape badly (residual {fit.residual:.2f} > "
                          f"{MAX_TEMPLATE_RESIDUAL})" + (f" in shape group {g}" if len(group_shapes) > 1 else ""))
        fits.append(fit)
    info = {"kind": "template", "template": source, "residual": round(max(f.residual for f in fits), 4),
            "matched_keypoints": min(f.matched for f in fits)}
    if len(fits) > 1:
        info["residual_per_group"] = [round(f.residual, 4) for f in fits]
    return CanonicalFrame("template", fits, info), ""


def canonical_frame(choice: str, class_name: str, keypoint_names: list, group_shapes: list, shape: torch.Tensor,
                    reflection: torch.Tensor | None, R: torch.Tensor, own_template: list | None = None,
                    templates: dict | None = None) -> CanonicalFrame:
    """The canonical frame of a class (:data:`FrameChoice` ``choice``), falling back down the list
    template -> symmetry+up -> sfm with the reason in ``info["fallback"]``.

    Args:
        group_shapes: every shape group's ``(K, 3)`` mean shape in the class (SfM) frame; shape: the
            class's mean shape; reflection: its symmetry plane (``None``: no flip pairs); R: ``(N, 3, 3)``
            the cameras with a view (SfM frame); own_template: the category's ``keypoints_3d``.
    """
    why = []
    if choice in ("best", "template"):
        found = template_points(class_name, keypoint_names, templates if templates is not None else load_templates(),
                                own_template)
        if found is None:
            why.append("no template for this class and its keypoint names")
        else:
            frame, reason = _template_frame(group_shapes, *found)
            if frame is not None:
                return frame
            why.append(reason)
    if choice in ("best", "template", "symmetry+up") and reflection is not None and len(R):
        fit, info = symmetry_up_frame(reflection, R, shape, keypoint_names)
        info = {"kind": "symmetry+up", **info}
        if why:
            info["fallback"] = "; ".join(why)
        return CanonicalFrame("symmetry+up", [fit], info)
    if reflection is None:
        why.append("no left/right keypoint pairs for a symmetry plane")
    info = {"kind": "sfm"}
    if why:
        info["fallback"] = "; ".join(why)
    return CanonicalFrame("sfm", [_identity()], info)


#: Berkeley PASCAL VOC keypoint names that are a PASCAL3D+ keypoint (each source is consistent within
#: itself, the two disagree on left and right: Berkeley's L_WingTip is PASCAL3D+'s right_wing). Found on
#: the 165 dev aeroplanes by projecting each object's CAD model with its true camera (docs/conventions.md).
VOC_ALIASES = {"aeroplane": {"NoseTip": "noselanding", "L_WingTip": "right_wing", "R_WingTip": "left_wing",
                             "L_Stabilizer": "right_elevator", "R_Stabilizer": "left_elevator",
                             "Top_Rudder": "rudder_upper", "Bot_Rudder": "tail", "Bot_Rudder_Front": "rudder_lower"}}


def main(argv=None) -> int:
    """``python -m carvi_torch.viewpoints.frame --build CAD_DIR [--out templates.json]``: the shipped templates."""
    import argparse

    from ..io.outputs import write_json
    from ..synthetic.meshes import load_models

    ap = argparse.ArgumentParser(prog="python -m carvi_torch.viewpoints.frame", description=main.__doc__)
    ap.add_argument("--build", required=True, metavar="CAD_DIR", help="PASCAL3D+ CAD models (.npz with keypoints)")
    ap.add_argument("--out", default=str(TEMPLATES_PATH), help="where to write (default: the shipped file)")
    args = ap.parse_args(argv)
    write_json(args.out, {"source": "PASCAL3D+ CAD models (Xiang, Mottaghi, Savarese 2014): each centred on its "
                                    "bounding box, scaled to a unit diagonal, keypoints averaged over the models",
                          "frame": "+z up, front towards -y (the PASCAL3D+ CAD frame)",
                          "classes": build_templates(load_models(args.build, strict=True)), "aliases": VOC_ALIASES})
    return 0


if __name__ == "__main__":
    from ..cli import run_command

    raise SystemExit(run_command(main, "interrupted; the templates file is as it was"))
