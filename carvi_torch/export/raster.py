"""A numpy z-buffer for the export's depth maps: the same pixels and the same depths as
:func:`carvi_torch.synthetic.render.rasterize_depth`, bit for bit, at a fraction of its cost on the
small triangles of a reconstruction's mesh (most cover no pixel centre at all).

The coverage rule and its exactness are :func:`carvi_torch.synthetic.render.rasterize_depth`'s: the
vertices are rounded to a dyadic grid fine enough that the float64 edge functions are exact, a pixel
centre on an edge is covered by both triangles, degenerate and non-finite triangles are skipped, and a
pixel's depth is the least barycentric interpolation of the vertex depths over the triangles that
cover it. The arithmetic is done in the same order, so the result is the same to the last bit (the
export's tests compare the two on real meshes and on random triangle soups). Numpy only: the export's
worker processes do not import torch.

Example (one triangle, depth 2 at every vertex; pixel centres on its edges are covered):
    >>> import numpy as np
    >>> xy = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]]); z = np.full(3, 2.0)
    >>> zbuffer(xy, z, np.array([[0, 1, 2]]), 3, 3)
    array([[ 2.,  2.,  2.],
           [ 2.,  2., inf],
           [ 2., inf, inf]], dtype=float32)
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["zbuffer"]


def _snap(xy: np.ndarray, height: int, width: int) -> np.ndarray:
    """``xy`` rounded to the grid of ``2^-m`` pixels, ``m = 25 - ceil(log2 R)`` (``R``: the largest of the
    image sides and the finite absolute coordinates), as the torch rasteriser rounds them."""
    finite = np.isfinite(xy)
    largest = float(np.abs(xy[finite]).max()) if finite.any() else 0.0
    m = 25 - math.ceil(math.log2(max(largest, float(width), float(height), 1.0)))
    return np.round(xy * 2.0 ** m) / 2.0 ** m


def _boxes(X: np.ndarray, Y: np.ndarray, height: int, width: int):
    """The triangles whose bounding box holds a pixel centre of the image, from their vertices' ``X``, ``Y``
    ``(3, F)``: their indices, the first pixel column and row of the box (clipped to the image) and the
    box's width and height in pixel centres. Non-finite triangles have none (NaN compares false, an
    infinite coordinate is caught here); degenerate ones are left to the caller."""
    x0 = np.clip(np.ceil(np.minimum(np.minimum(X[0], X[1]), X[2])), 0, width)
    x1 = np.clip(np.floor(np.maximum(np.maximum(X[0], X[1]), X[2])), -1, width - 1)
    y0 = np.clip(np.ceil(np.minimum(np.minimum(Y[0], Y[1]), Y[2])), 0, height)
    y1 = np.clip(np.floor(np.maximum(np.maximum(Y[0], Y[1]), Y[2])), -1, height - 1)
    keep = np.flatnonzero((x1 >= x0) & (y1 >= y0))
    keep = keep[np.isfinite(X[:, keep]).all(axis=0) & np.isfinite(Y[:, keep]).all(axis=0)]
    return keep, x0[keep], y0[keep], (x1[keep] - x0[keep] + 1).astype(np.int64), \
        (y1[keep] - y0[keep] + 1).astype(np.int64)


def zbuffer(xy: np.ndarray, depth: np.ndarray, faces: np.ndarray, height: int, width: int) -> np.ndarray:
    """Smallest depth of the triangles covering each pixel centre.

    Args:
        xy: ``(V, 2)`` pixel coordinates ``(x, y)`` (pixel ``[i, j]`` has its centre at ``x = j, y = i``).
        depth: ``(V,)`` vertex depths.
        faces: ``(F, 3)`` integer vertex indices.
        height, width: image size.

    Returns:
        ``(height, width)`` float32, ``+inf`` where no triangle covers the pixel centre.
    """
    xy = np.asarray(xy, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    height, width = int(height), int(width)
    zbuf = np.full(height * width, np.inf)
    P = _snap(xy, height, width)
    ft = np.ascontiguousarray(faces.T)  # (3, F): one contiguous row per corner
    keep, x0, y0, bw, bh = _boxes(P[:, 0][ft], P[:, 1][ft], height, width)
    X, Y = P[:, 0][ft[:, keep]], P[:, 1][ft[:, keep]]
    area2 = (X[1] - X[0]) * (Y[2] - Y[0]) - (Y[1] - Y[0]) * (X[2] - X[0])
    nondegenerate = area2 != 0
    keep, x0, y0, bw, bh, X, Y, area2 = (keep[nondegenerate], x0[nondegenerate], y0[nondegenerate],
                                         bw[nondegenerate], bh[nondegenerate], X[:, nondegenerate],
                                         Y[:, nondegenerate], area2[nondegenerate])
    if len(keep) == 0:
        return zbuf.reshape(height, width).astype(np.float32)
    flip = area2 < 0  # orient counter-clockwise: swap the second and third vertex
    bx, cx = np.where(flip, X[2], X[1]), np.where(flip, X[1], X[2])
    by, cy = np.where(flip, Y[2], Y[1]), np.where(flip, Y[1], Y[2])
    count = bw * bh
    owner = np.repeat(np.arange(len(keep)), count)  # one row per candidate pixel centre
    k = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count)
    w = bw[owner]
    px = x0[owner] + k % w
    py = y0[owner] + k // w
    ax, ay, bx, by, cx, cy = X[0][owner], Y[0][owner], bx[owner], by[owner], cx[owner], cy[owner]
    e_a = (cx - bx) * (py - by) - (cy - by) * (px - bx)  # opposite A
    e_b = (ax - cx) * (py - cy) - (ay - cy) * (px - cx)  # opposite B
    e_c = (bx - ax) * (py - ay) - (by - ay) * (px - ax)  # opposite C
    inside = np.flatnonzero((e_a >= 0) & (e_b >= 0) & (e_c >= 0))
    o = owner[inside]
    area = np.abs(area2)[o]
    wa, wb, wc = e_a[inside] / area, e_b[inside] / area, e_c[inside] / area
    fl = flip[o]
    w1, w2 = np.where(fl, wc, wb), np.where(fl, wb, wc)  # weights in the face's own vertex order
    dv = np.asarray(depth, dtype=np.float64)[faces[keep[o]]]
    z = wa * dv[:, 0] + w1 * dv[:, 1] + w2 * dv[:, 2]
    np.minimum.at(zbuf, (py[inside] * width + px[inside]).astype(np.int64), z)
    return zbuf.reshape(height, width).astype(np.float32)
