"""Embedded procedural object classes: car, aeroplane, chair, bottle.

Every instance is an implicit union of parts (boxes, ellipsoids, cylinders, some of
them sheared or cut by planes) with random proportions, evaluated as a signed-distance
-like function on a grid (torch) and meshed with skimage's marching cubes: meshes are
watertight, with no internal faces. Semantic keypoints are defined on the parts and
pulled onto the zero level set by Newton steps on the implicit function, so they lie on
the surface (within a fraction of a voxel of the mesh).

Object frame as PASCAL3D+: +z up, front towards -y, centred on its bounding box and
scaled to a bounding-box diagonal of 1. "left" is the -x side (PASCAL3D+'s usual naming:
the left keypoints appear on the image's left in a frontal view).

Keypoints (names as in PASCAL3D+ where the class exists there):

* ``car`` (16): ``{left,right}_{front,back}_wheel``, ``{left,right}_front_light``,
  ``{left,right}_back_trunk``, ``{upper,lower}_{left,right}_windshield``,
  ``{upper,lower}_{left,right}_rearwindow``.
* ``aeroplane`` (8): ``noselanding``, ``tail``, ``rudder_upper``, ``rudder_lower``,
  ``{left,right}_wing``, ``{left,right}_elevator`` (tips).
* ``chair`` (10): ``back_upper_{left,right}``, ``seat_upper_{left,right}`` (back corners
  of the seat), ``seat_lower_{left,right}`` (front corners), ``leg_upper_{left,right}``
  (back feet), ``leg_lower_{left,right}`` (front feet).
* ``bottle`` (9, rotationally symmetric, view-dependent keypoints in one plane like
  PASCAL's): ``mouth``, ``body``, ``bottom`` at the front (-y) and their ``_left`` /
  ``_right`` at -x / +x.

:func:`write_default_collection` renders ``instances_per_class`` instances of each class
once (each its own ``object_id``), the data ``python -m carvi_torch.reconstruct`` uses
when given no ``--data``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch

from .meshes import Model
from .render import DEFAULT_IMAGE_SIZE, RENDER_VERSION, render_dataset, seed_generator

__all__ = ["CATEGORIES", "make_instance", "make_collection", "write_default_collection", "mesh_implicit"]

#: The embedded classes.
CATEGORIES = ("aeroplane", "bottle", "car", "chair")

SDF = Callable[[torch.Tensor], torch.Tensor]

# --------------------------------------------------------------------------- primitives
# Each takes points p (..., 3) and returns (...,): negative inside, zero on the surface.


def _box(p: torch.Tensor, center, half, rounding: float = 0.0) -> torch.Tensor:
    """Exact distance to a box (edges rounded by ``rounding``), axis-aligned."""
    c = p.new_tensor(center)
    h = p.new_tensor(half) - rounding
    q = (p - c).abs() - h
    return q.clamp(min=0).norm(dim=-1) + q.amax(dim=-1).clamp(max=0) - rounding


def _ellipsoid(p: torch.Tensor, center, radii) -> torch.Tensor:
    """Ellipsoid (a distance bound with the exact zero set)."""
    r = p.new_tensor(radii)
    q = (p - p.new_tensor(center)) / r
    k0 = q.norm(dim=-1)
    k1 = (q / r).norm(dim=-1).clamp(min=1e-12)
    return k0 * (k0 - 1.0) / k1


def _cylinder(p: torch.Tensor, center, axis: int, radius: float, half_length: float,
              rounding: float = 0.0) -> torch.Tensor:
    """Exact distance to a capped cylinder along coordinate ``axis`` (rims rounded by ``rounding``)."""
    q = p - p.new_tensor(center)
    others = [i for i in range(3) if i != axis]
    d = torch.stack([q[..., others].norm(dim=-1) - (radius - rounding), q[..., axis].abs() - (half_length - rounding)],
                    dim=-1)
    return d.clamp(min=0).norm(dim=-1) + d.amax(dim=-1).clamp(max=0) - rounding


def _halfspace(p: torch.Tensor, point, normal) -> torch.Tensor:
    """Signed distance to a plane, positive on the side ``normal`` points to."""
    n = p.new_tensor(normal)
    n = n / n.norm()
    return (p - p.new_tensor(point)) @ n


def _shear(p: torch.Tensor, target: int, source: int, k: float, origin: float = 0.0, absolute: bool = False):
    """Points with ``p[target] -= k * (p[source] - origin)`` (or ``k * |p[source]|``)."""
    q = p.clone()
    s = p[..., source].abs() if absolute else p[..., source] - origin
    q[..., target] = p[..., target] - k * s
    return q


@dataclass
class _Part:
    """One primitive: ``fn`` (points ``(..., 3)`` -> values) and a box ``[lo, hi]`` holding its solid."""

    fn: SDF
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


def _box_part(center, half, rounding: float = 0.0) -> _Part:
    c, h = np.asarray(center, float), np.asarray(half, float)
    return _Part(lambda p: _box(p, center, half, rounding), tuple(c - h), tuple(c + h))


def _cylinder_part(center, axis: int, radius: float, half_length: float, rounding: float = 0.0) -> _Part:
    c = np.asarray(center, float)
    h = np.full(3, radius)
    h[axis] = half_length
    return _Part(lambda p: _cylinder(p, center, axis, radius, half_length, rounding), tuple(c - h), tuple(c + h))


def _ellipsoid_part(center, radii) -> _Part:
    c, r = np.asarray(center, float), np.asarray(radii, float)
    return _Part(lambda p: _ellipsoid(p, center, radii), tuple(c - r), tuple(c + r))


@dataclass
class _Shape:
    """An implicit shape in raw units: the union of ``parts``, its keypoints, its thinnest part."""

    parts: list[_Part]
    keypoints: dict[str, tuple[float, float, float]]
    min_feature: float  # thinnest part (raw units), sets the grid spacing

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        """Union (minimum) of the parts at points ``(..., 3)``."""
        out = self.parts[0].fn(p)
        for part in self.parts[1:]:
            out = torch.minimum(out, part.fn(p))
        return out

    @property
    def lo(self) -> np.ndarray:
        return np.min([part.lo for part in self.parts], axis=0)

    @property
    def hi(self) -> np.ndarray:
        return np.max([part.hi for part in self.parts], axis=0)


def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand(1, generator=g, dtype=torch.float64))


def _chance(g: torch.Generator, p: float) -> bool:
    return float(torch.rand(1, generator=g, dtype=torch.float64)) < p


_SIDES = (("left", -1.0), ("right", 1.0))


def _car(g: torch.Generator) -> _Shape:
    L = 1.0
    W = L * _uniform(g, 0.38, 0.46)
    rw = L * _uniform(g, 0.075, 0.10)  # wheel radius
    ww = L * _uniform(g, 0.05, 0.08)  # wheel width
    z0 = rw * _uniform(g, 0.55, 0.9)  # body bottom
    hb = L * _uniform(g, 0.13, 0.20)  # body height
    z1 = z0 + hb
    yf = -L / 2 + L * _uniform(g, 0.15, 0.22)
    yb = L / 2 - L * _uniform(g, 0.15, 0.24)
    xw = W / 2 - ww / 2 + 0.01 * L
    hc = L * _uniform(g, 0.11, 0.18)  # cabin height
    lc = L * _uniform(g, 0.45, 0.65)  # cabin length at its base
    yc = L * _uniform(g, -0.03, 0.12)  # cabin centre (towards the back)
    wc = W * _uniform(g, 0.78, 0.9)
    run_f = hc * _uniform(g, 0.6, 1.4)  # windshield slant
    run_r = hc * _uniform(g, 0.2, 1.0)
    room = lc - 0.15 * L
    if run_f + run_r > room:
        f = room / (run_f + run_r)
        run_f, run_r = run_f * f, run_r * f
    rb = min(0.03, hb / 4)
    ycf, ycr = yc - lc / 2, yc + lc / 2  # cabin base, front and rear

    def cabin(p):
        d = _box(p, (0, yc, z1 + hc / 2 - 0.01), (wc / 2, lc / 2, hc / 2 + 0.01), 0.012)
        d = torch.maximum(d, _halfspace(p, (0, ycf, z1), (0, -hc, run_f)))
        return torch.maximum(d, _halfspace(p, (0, ycr, z1), (0, hc, run_r)))

    parts = [_box_part((0, 0, (z0 + z1) / 2), (W / 2, L / 2, hb / 2), rb),
             _Part(cabin, (-wc / 2, ycf, z1 - 0.02), (wc / 2, ycr, z1 + hc))]
    parts += [_cylinder_part((sx * xw, y, rw), 0, rw, ww / 2, 0.01) for sx in (-1, 1) for y in (yf, yb)]
    kp = {}
    for side, sx in _SIDES:
        kp[f"{side}_front_wheel"] = (sx * (xw + ww / 2), yf, rw)
        kp[f"{side}_back_wheel"] = (sx * (xw + ww / 2), yb, rw)
        kp[f"{side}_front_light"] = (sx * W / 2 * 0.72, -L / 2, z0 + 0.62 * hb)
        kp[f"{side}_back_trunk"] = (sx * W / 2 * 0.8, L / 2, z1)
        kp[f"upper_{side}_windshield"] = (sx * wc / 2, ycf + run_f, z1 + hc)
        kp[f"lower_{side}_windshield"] = (sx * wc / 2, ycf, z1)
        kp[f"upper_{side}_rearwindow"] = (sx * wc / 2, ycr - run_r, z1 + hc)
        kp[f"lower_{side}_rearwindow"] = (sx * wc / 2, ycr, z1)
    return _Shape(parts, kp, min_feature=ww)


_PLANE_LENGTH = 1.0  # fuselage length, nose to tail (raw units)


@dataclass(frozen=True)
class _PlaneDims:
    """An aeroplane's random dimensions (raw units): fuselage, wing, fin, elevator (tailplane), engines."""

    rf: float  # fuselage radius
    ln: float  # nose length
    lt: float  # tail cone length
    span: float  # wing: span, chord, thickness, sweep and dihedral (per unit |x|), centre (y, z)
    chord: float
    tw: float
    sweep: float
    dihedral: float
    yw: float
    zw: float
    hf: float  # fin: height above the fuselage, chord, sweep, centre y
    cf: float
    kf: float
    yfin: float
    se: float  # elevator: span, chord, sweep, thickness, centre (y, z)
    ce: float
    ke: float
    te: float
    ye: float
    ze: float
    engines: bool  # two engines under the wings: x offset, radius, length
    xe: float
    re: float
    le: float


def _plane_dims(g: torch.Generator) -> _PlaneDims:
    """Draw an aeroplane's dimensions from ``g`` (a T-tail one time in five, engines one in two)."""
    rf = _uniform(g, 0.045, 0.075)  # fuselage radius
    ln = _uniform(g, 0.08, 0.16)  # nose length
    lt = _uniform(g, 0.2, 0.3)  # tail cone length
    span = _uniform(g, 0.75, 1.05)
    chord = _uniform(g, 0.12, 0.2)
    tw = _uniform(g, 0.022, 0.032)
    sweep = _uniform(g, 0.0, 0.45)
    dihedral = _uniform(g, 0.0, 0.1)
    yw = _uniform(g, -0.08, 0.06)
    zw = rf * _uniform(g, -0.6, 0.5)
    t_tail = _chance(g, 0.2)
    hf = _uniform(g, 0.12, 0.22)  # fin height above the fuselage
    cf = _uniform(g, 0.12, 0.2)
    kf = _uniform(g, 0.3, 1.0)  # fin sweep
    yfin = _PLANE_LENGTH / 2 - cf / 2 - _uniform(g, 0.0, 0.04)
    se = span * _uniform(g, 0.3, 0.45)  # elevator span
    ce = chord * _uniform(g, 0.5, 0.7)
    ke = _uniform(g, 0.0, 0.5)
    te = max(0.02, 0.8 * tw)
    if t_tail:
        ze = rf + hf - te / 2
        ye = yfin + kf * hf
    else:
        ze = rf * _uniform(g, 0.0, 0.5)
        ye = _PLANE_LENGTH / 2 - ce / 2 - _uniform(g, 0.02, 0.06)
    engines = _chance(g, 0.5)
    xe = span * _uniform(g, 0.18, 0.3)
    re = _uniform(g, 0.025, 0.04)
    le = _uniform(g, 0.12, 0.2)
    return _PlaneDims(rf, ln, lt, span, chord, tw, sweep, dihedral, yw, zw, hf, cf, kf, yfin, se, ce, ke, te, ye, ze,
                      engines, xe, re, le)


def _plane_parts(d: _PlaneDims) -> list[_Part]:
    """Fuselage (cylinder, nose and tail cone), wing, elevator, fin and the engines of an aeroplane."""
    yn, yt = -_PLANE_LENGTH / 2 + d.ln, _PLANE_LENGTH / 2 - d.lt  # cylinder ends

    def wing(p):  # swept back and raised (dihedral) with |x|
        q = _shear(_shear(p, 1, 0, d.sweep, absolute=True), 2, 0, d.dihedral, absolute=True)
        return _box(q, (0, d.yw, d.zw), (d.span / 2, d.chord / 2, d.tw / 2))

    def elevator(p):
        return _box(_shear(p, 1, 0, d.ke, absolute=True), (0, d.ye, d.ze), (d.se / 2, d.ce / 2, d.te / 2))

    def fin(p):  # from the fuselage axis up, swept back above the fuselage top
        return _box(_shear(p, 1, 2, d.kf, origin=d.rf), (0, d.yfin, (d.rf + d.hf) / 2),
                    (d.te / 2, d.cf / 2, (d.rf + d.hf) / 2))

    parts = [
        _cylinder_part((0, (yn + yt) / 2, 0), 1, d.rf, (yt - yn) / 2),
        _ellipsoid_part((0, yn, 0), (d.rf, d.ln, d.rf)),
        _ellipsoid_part((0, yt, 0), (d.rf, d.lt, d.rf)),
        _Part(wing, (-d.span / 2, d.yw - d.chord / 2, d.zw - d.tw / 2),
              (d.span / 2, d.yw + d.chord / 2 + d.sweep * d.span / 2, d.zw + d.tw / 2 + d.dihedral * d.span / 2)),
        _Part(elevator, (-d.se / 2, d.ye - d.ce / 2, d.ze - d.te / 2),
              (d.se / 2, d.ye + d.ce / 2 + d.ke * d.se / 2, d.ze + d.te / 2)),
        _Part(fin, (-d.te / 2, d.yfin - d.cf / 2 - d.kf * d.rf, 0.0),
              (d.te / 2, d.yfin + d.cf / 2 + d.kf * d.hf, d.rf + d.hf)),
    ]
    if d.engines:
        y_e = d.yw + d.sweep * d.xe - 0.03
        z_e = d.zw + d.dihedral * d.xe - d.tw / 2 - d.re * 0.8
        parts += [_cylinder_part((sx * d.xe, y_e, z_e), 1, d.re, d.le / 2, 0.01) for sx in (-1, 1)]
    return parts


def _plane_keypoints(d: _PlaneDims) -> dict[str, tuple[float, float, float]]:
    """The aeroplane's keypoints: nose gear, tail, rudder ends, wing and elevator tips."""
    kp = {
        "noselanding": (0.0, -_PLANE_LENGTH / 2 + 0.15 * d.ln, -0.5 * d.rf),
        "tail": (0.0, _PLANE_LENGTH / 2, 0.0),
        "rudder_upper": (0.0, d.yfin + d.cf / 2 + d.kf * d.hf, d.rf + d.hf),
        "rudder_lower": (0.0, d.yfin - d.cf / 2, d.rf),
    }
    for side, sx in _SIDES:
        kp[f"{side}_wing"] = (sx * d.span / 2, d.yw + d.sweep * d.span / 2, d.zw + d.dihedral * d.span / 2)
        kp[f"{side}_elevator"] = (sx * d.se / 2, d.ye + d.ke * d.se / 2, d.ze)
    return kp


def _aeroplane(g: torch.Generator) -> _Shape:
    d = _plane_dims(g)
    return _Shape(_plane_parts(d), _plane_keypoints(d), min_feature=min(d.tw, d.te))


def _chair(g: torch.Generator) -> _Shape:
    ws = _uniform(g, 0.42, 0.55)  # seat width (x)
    ds = _uniform(g, 0.40, 0.52)  # seat depth (y)
    ts = _uniform(g, 0.035, 0.07)  # seat thickness
    hs = _uniform(g, 0.40, 0.50)  # seat top height
    tl = _uniform(g, 0.03, 0.05)  # leg thickness
    inset = _uniform(g, 0.0, 0.03)
    round_legs = _chance(g, 0.4)
    wb = ws * _uniform(g, 0.8, 1.0)  # back width
    tb = _uniform(g, 0.03, 0.06)
    hb = _uniform(g, 0.35, 0.55)  # back height above the seat
    tilt = _uniform(g, 0.0, 0.25)
    arms = _chance(g, 0.3)
    za = hs + _uniform(g, 0.17, 0.25)
    lx = ws / 2 - inset - tl / 2
    ly = ds / 2 - inset - tl / 2
    yb = ds / 2 - tb / 2  # back panel centre (at seat height)
    leg_top = hs - ts / 2
    z_lo = hs - ts  # the back starts at the seat's underside

    def back(p):  # tilted backwards above the seat
        q = _shear(p, 1, 2, tilt, origin=hs)
        return _box(q, (0, yb, (z_lo + hs + hb) / 2), (wb / 2, tb / 2, (hs + hb - z_lo) / 2), 0.008)

    parts = [_box_part((0, 0, hs - ts / 2), (ws / 2, ds / 2, ts / 2), 0.006),
             _Part(back, (-wb / 2, yb - tb / 2 - tilt * ts, z_lo), (wb / 2, yb + tb / 2 + tilt * hb, hs + hb))]
    for sx in (-1, 1):
        for sy in (-1, 1):
            if round_legs:
                parts.append(_cylinder_part((sx * lx, sy * ly, leg_top / 2), 2, tl / 2, leg_top / 2))
            else:
                parts.append(_box_part((sx * lx, sy * ly, leg_top / 2), (tl / 2, tl / 2, leg_top / 2)))
    if arms:
        for sx in (-1, 1):
            x = sx * (ws / 2 - 0.02)
            parts.append(_box_part((x, 0.0, za), (0.02, ds / 2 - 0.02, 0.02)))
            parts.append(_box_part((x, -ds / 2 + 0.05, (hs + za) / 2), (0.015, 0.015, (za - hs) / 2 + 0.01)))
    kp = {}
    for side, sx in _SIDES:
        kp[f"back_upper_{side}"] = (sx * wb / 2, yb + tilt * hb, hs + hb)
        kp[f"seat_upper_{side}"] = (sx * ws / 2, ds / 2 - tb - 0.01, hs)
        kp[f"seat_lower_{side}"] = (sx * ws / 2, -ds / 2, hs)
        kp[f"leg_upper_{side}"] = (sx * lx, ly, 0.0)
        kp[f"leg_lower_{side}"] = (sx * lx, -ly, 0.0)
    return _Shape(parts, kp, min_feature=min(tl, tb, ts))


def _bottle(g: torch.Generator) -> _Shape:
    H = 1.0
    rb = _uniform(g, 0.11, 0.17)  # body radius
    hbody = _uniform(g, 0.40, 0.60)  # straight body height
    hsh = _uniform(g, 0.08, 0.20)  # shoulder height
    rn = rb * _uniform(g, 0.25, 0.45)  # neck radius
    lip = _chance(g, 0.6)
    rl = rn * 1.2
    r_top = rl if lip else rn
    parts = [
        _cylinder_part((0, 0, hbody / 2), 2, rb, hbody / 2, 0.02),
        _ellipsoid_part((0, 0, hbody), (rb, rb, hsh)),
        _cylinder_part((0, 0, (hbody + H) / 2), 2, rn, (H - hbody) / 2),
    ]
    if lip:
        parts.append(_cylinder_part((0, 0, H - 0.015), 2, rl, 0.015))
    kp = {}
    for name, r, z in (("mouth", r_top, H), ("body", rb, hbody), ("bottom", rb, 0.0)):
        kp[name] = (0.0, -r, z)
        kp[f"{name}_left"] = (-r, 0.0, z)
        kp[f"{name}_right"] = (r, 0.0, z)
    return _Shape(parts, kp, min_feature=2 * rn)


_BUILDERS: dict[str, Callable[[torch.Generator], _Shape]] = {
    "aeroplane": _aeroplane, "bottle": _bottle, "car": _car, "chair": _chair,
}


# --------------------------------------------------------------------------- meshing


def mesh_implicit(parts: Sequence[_Part], spacing: float, pad: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the zero level set of a union of parts (CPU-side).

    The grid (``spacing``) covers the parts' boxes grown by ``pad`` cells, so the surface
    never touches its border and the mesh is closed. Each part is evaluated (float32,
    torch) only on the grid block of its own box grown by ``pad`` cells and folded in by
    a minimum; grid points outside every block keep a positive value. Marching cubes
    only interpolates along grid edges that cross the surface, whose two ends lie within
    one cell of it, hence inside the block of the part that makes the surface there: the
    mesh equals the one of the fully evaluated union. skimage's marching cubes (Lewiner)
    extracts it with outward normals (``gradient_direction="descent"``: values descend
    into the object).

    Args:
        parts: primitives with their boxes.
        spacing: grid step.
        pad: cells of margin (``>= 2``).

    Returns:
        ``vertices (V, 3) float64`` and ``faces (F, 3) int64`` (numpy).
    """
    from skimage.measure import marching_cubes

    if pad < 2:
        raise ValueError(f"pad must be >= 2, got {pad}")
    lo = np.min([p.lo for p in parts], axis=0) - pad * spacing
    hi = np.max([p.hi for p in parts], axis=0) + pad * spacing
    n = np.maximum(np.ceil((hi - lo) / spacing).astype(int) + 1, 2)
    axes = [torch.arange(int(k), dtype=torch.float32) * spacing + float(o) for k, o in zip(n, lo)]
    vol = torch.full(tuple(int(k) for k in n), float(pad * spacing), dtype=torch.float32)
    for part in parts:
        i0 = np.clip(np.floor((np.asarray(part.lo) - lo) / spacing).astype(int) - pad, 0, n)
        i1 = np.clip(np.ceil((np.asarray(part.hi) - lo) / spacing).astype(int) + pad + 1, 0, n)
        sl = tuple(slice(int(a), int(b)) for a, b in zip(i0, i1))
        block = torch.stack(torch.meshgrid(*(ax[s] for ax, s in zip(axes, sl)), indexing="ij"), dim=-1)
        vol[sl] = torch.minimum(vol[sl], part.fn(block))
    verts, faces, _normals, _values = marching_cubes(vol.numpy(), level=0.0, spacing=(spacing,) * 3,
                                                     gradient_direction="descent", allow_degenerate=False)
    return verts.astype(np.float64) + lo, faces.astype(np.int64)


def _snap_to_surface(sdf: SDF, points: torch.Tensor, steps: int = 8, h: float = 1e-6) -> torch.Tensor:
    """Newton steps ``p <- p - f(p) grad f / |grad f|^2`` onto the zero level set (float64).

    The gradient is a central difference with step ``h``; all ``7 K`` evaluations of a
    step are one batched call.
    """
    p = points.detach().to(torch.float64).clone()
    offsets = torch.cat([torch.zeros(1, 3, dtype=torch.float64), h * torch.eye(3, dtype=torch.float64),
                         -h * torch.eye(3, dtype=torch.float64)])  # (7, 3)
    for _ in range(steps):
        f = sdf(p[:, None, :] + offsets)  # (K, 7)
        grad = (f[:, 1:4] - f[:, 4:7]) / (2 * h)
        p = p - (f[:, 0] / grad.pow(2).sum(-1).clamp(min=1e-12))[:, None] * grad
    return p


def make_instance(category: str, generator: torch.Generator, name: str | None = None,
                  cells_per_feature: float = 1.7, min_cells: int = 48, max_cells: int = 96) -> Model:
    """One random instance of a procedural class, meshed and with its keypoints.

    The grid spacing is the thinnest part's thickness over ``cells_per_feature`` (thin
    parts stay at least that many cells thick), with ``min_cells`` to ``max_cells`` cells
    along the longest side. The mesh is then centred on its bounding box and scaled to a
    bounding-box diagonal of 1 (PASCAL3D+'s normalisation); keypoints follow.

    Args:
        category: one of :data:`CATEGORIES`.
        generator: CPU ``torch.Generator`` (all shape parameters come from it).
        name: model name (default: the category).
        cells_per_feature: grid cells across the thinnest part.
        min_cells, max_cells: bounds on the grid size along the longest side.

    Returns:
        :class:`~carvi_torch.synthetic.meshes.Model` with a watertight mesh,
        ``source = "procedural:<name>"``.

    Example:
        >>> m = make_instance("car", torch.Generator().manual_seed(0))
        >>> m.category, len(m.keypoint_names)
        ('car', 16)
    """
    if category not in _BUILDERS:
        raise ValueError(f"category must be one of {CATEGORIES}, got {category!r}")
    shape = _BUILDERS[category](generator)
    extent = max(h - l for l, h in zip(shape.lo, shape.hi))
    if not 2 <= min_cells <= max_cells:
        raise ValueError(f"need 2 <= min_cells <= max_cells, got {min_cells}, {max_cells}")
    spacing = min(shape.min_feature / cells_per_feature, extent / (min_cells - 1))
    spacing = max(spacing, extent / (max_cells - 1))
    verts, faces = mesh_implicit(shape.parts, spacing)
    names = list(shape.keypoints)
    kp = _snap_to_surface(shape.sdf, torch.tensor([shape.keypoints[n] for n in names], dtype=torch.float64))
    vmin, vmax = verts.min(axis=0), verts.max(axis=0)
    centre = (vmin + vmax) / 2
    scale = 1.0 / float(np.linalg.norm(vmax - vmin))
    verts = (verts - centre) * scale
    kp = (kp.numpy() - centre) * scale
    return Model(name=name or category, category=category, vertices=torch.from_numpy(verts.astype(np.float32)),
                 faces=torch.from_numpy(faces), keypoint_names=names,
                 keypoints=torch.from_numpy(kp.astype(np.float32)), source=f"procedural:{name or category}")


def make_collection(instances_per_class: int = 40, seed: int = 0,
                    categories: Sequence[str] | None = None) -> list[Model]:
    """``instances_per_class`` instances of each class, named ``<class><index:03d>``.

    Instance ``i`` of class ``c`` is built from :func:`seed_generator`
    ``(seed, "procedural", c, i)``, so it does not depend on the other classes or on how
    many instances are asked for.
    """
    cats = list(categories) if categories is not None else list(CATEGORIES)
    bad = [c for c in cats if c not in _BUILDERS]
    if bad:
        raise ValueError(f"unknown procedural categories {bad}; choose from {CATEGORIES}")
    if instances_per_class < 1:
        raise ValueError(f"instances_per_class must be >= 1, got {instances_per_class}")
    return [make_instance(c, seed_generator(int(seed), "procedural", c, i), name=f"{c}{i:03d}")
            for c in cats for i in range(instances_per_class)]


def write_default_collection(out_dir: str | Path, instances_per_class: int = 40, views_per_instance: int = 1,
                             seed: int = 0, categories: Sequence[str] | None = None,
                             image_size: int | Sequence[int] = DEFAULT_IMAGE_SIZE, test_views: int = 0,
                             keypoint_noise: float = 0.0, boundary_noise: float = 0.0, progress: bool = False,
                             device: str | torch.device = "cpu") -> dict:
    """Build the procedural classes and render them into a COCO dataset (VOC-like).

    Many different instances, ``views_per_instance`` photographs each (default one),
    every instance its own ``object_id``; written by
    :func:`~carvi_torch.synthetic.render.render_dataset` (``annotations.json``,
    ``gt.json``, ``meshes/``).

    Returns:
        :func:`render_dataset`'s summary dict, plus ``build_seconds`` (meshing time).
    """
    import time

    from ..runtime import torch_threads

    # One torch thread: thousands of small tensor ops, which a second intra-op thread only slows down (the same
    # files, byte for byte; the default collection in 4.4-6.2 s against 15.8-30.8 s on the loaded 2-core host).
    with torch_threads(1):
        t0 = time.perf_counter()
        models = make_collection(instances_per_class, seed, categories)
        t_build = time.perf_counter() - t0
        summary = render_dataset(models, out_dir, views=views_per_instance, test_views=test_views, seed=seed,
                                 image_size=image_size, keypoint_noise=keypoint_noise,
                                 boundary_noise=boundary_noise, progress=progress, device=device)
    summary["build_seconds"] = t_build
    summary["seconds"] = summary["seconds"] + t_build
    return summary


#: The version of the procedural shapes: raise it when :func:`make_instance` builds other shapes for the same
#: ``(seed, class, index)``, so that a run's ``input`` folder made by an older one is generated again.
GENERATOR_VERSION = 1
#: The record, in the folder of :func:`default_collection`, of the settings its collection was generated with.
GENERATION_RECORD = "procedural.json"


def generation_settings(instances_per_class: int, seed: int) -> dict:
    """What :func:`default_collection` records (and compares) of a generated collection.

    Example:
        >>> generation_settings(40, 0)["instances_per_class"], generation_settings(40, 0)["seed"]
        (40, 0)
    """
    return {"generator_version": GENERATOR_VERSION, "render_version": RENDER_VERSION,
            "instances_per_class": int(instances_per_class), "seed": int(seed), "categories": list(CATEGORIES)}


def _generated_with(target: Path) -> dict | None:
    """The settings recorded in ``target`` (None: no readable record)."""
    import json

    try:
        got = json.loads((target / GENERATION_RECORD).read_text())
    except (OSError, ValueError):
        return None
    return got if isinstance(got, dict) else None


def _why_generate(target: Path, wanted: dict) -> str | None:
    """Why the collection in ``target`` is to be generated (None: it is complete and made with ``wanted``)."""
    from ..io.outputs import is_done

    if not is_done(target / "annotations.json", target / "gt.json"):
        return "not generated yet"
    got = _generated_with(target)
    if got is None:
        return f"no record of its settings ({GENERATION_RECORD})"
    diff = sorted(k for k in wanted.keys() | got.keys() if got.get(k) != wanted.get(k))
    if diff:
        return "made with other settings: " + ", ".join(f"{k} {got.get(k)} there, {wanted.get(k)} now" for k in diff)
    return None


def default_collection(target: str | Path, instances_per_class: int, seed: int, progress: bool = False,
                       log=print) -> tuple[Path, Path]:
    """``annotations.json`` and ``gt.json`` of the embedded default collection in ``target``, generated
    there (:func:`write_default_collection`) unless it is complete and its record (:data:`GENERATION_RECORD`)
    holds these settings (:func:`generation_settings`): a rerun into the same folder with another ``seed`` or
    ``instances_per_class`` generates the collection again, its earlier files removed first. A collection
    generated once is kept in the user's cache (:mod:`carvi_torch.synthetic.cache`, keyed by the settings and the
    code) and copied from there, the same files byte for byte."""
    import shutil

    from ..io.outputs import write_json
    from . import cache

    target = Path(target)
    ann = target / "annotations.json"
    wanted = generation_settings(instances_per_class, seed)
    why = _why_generate(target, wanted)
    if why is not None:
        what = f"the embedded procedural collection ({instances_per_class} instances per class, seed {seed})"
        (target / GENERATION_RECORD).unlink(missing_ok=True)  # written last: a cut-short generation has none
        for old in (ann, target / "gt.json"):
            old.unlink(missing_ok=True)
        shutil.rmtree(target / "meshes", ignore_errors=True)
        key = cache.collection_key(wanted)
        files = cache.load_files(key)
        if files is not None:
            log(f"copying {what} from the cache ({cache.entry_path(key).parent}) to {target}: {why}")
            _write_files(target, files)
        else:
            log(f"generating {what} in {target}: {why}")
            write_default_collection(target, instances_per_class=instances_per_class, seed=seed, progress=progress)
            try:
                cache.store_files(key, _collection_files(target))
            except OSError as e:  # the cache is a convenience: never the run's end
                log(f"warning: the collection was not kept in the cache: {e}")
        write_json(target / GENERATION_RECORD, wanted)
    return ann, target / "gt.json"


def _collection_files(target: Path) -> dict[str, bytes]:
    """What :func:`write_default_collection` wrote in ``target``: relative name -> bytes."""
    paths = [target / "annotations.json", target / "gt.json", *sorted((target / "meshes").iterdir())]
    return {p.relative_to(target).as_posix(): p.read_bytes() for p in paths}


def _write_files(target: Path, files: dict[str, bytes]) -> None:
    """Write a cached collection's ``files`` into ``target``, ``annotations.json`` last (it marks the folder
    complete, as :func:`~carvi_torch.synthetic.render.render_dataset` writes it)."""
    from ..io.outputs import write_bytes

    for name in sorted(files, key=lambda n: (n == "annotations.json", n)):
        write_bytes(target / name, files[name], sync=not name.startswith("meshes/"))
