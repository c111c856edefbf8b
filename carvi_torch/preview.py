"""``preview.png``: a few reconstructions at a glance.

Per object (a row): the input mask with its keypoints, the reconstruction's silhouette
projected back onto the mask (green = both, red = mask only, blue = reconstruction only),
and two shaded views of the voxel shape (the reference view turned by 90 degrees about
the image y axis — a side view — and a view from above).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["write_preview", "shaded_view", "silhouette_overlay", "project_silhouette", "overlay_colours",
           "crop_box", "OVERLAY_COLOURS"]


def shaded_view(occupancy: np.ndarray, axis: int, flip: bool = False) -> np.ndarray:
    """Depth-shaded orthographic view of ``occupancy (D, H, W)`` looking along ``axis``.

    Returns an ``(a, b)`` float image in [0, 1] (1 = nearest surface, 0 = background).
    """
    occ = np.flip(occupancy, axis=axis) if flip else occupancy
    n = occ.shape[axis]
    hit = occ.any(axis=axis)
    first = np.argmax(occ, axis=axis).astype(np.float32)
    shade = 1.0 - 0.7 * first / max(n - 1, 1)
    gy, gx = np.gradient(np.where(hit, first, first.max() if hit.any() else 0.0))
    light = np.clip(1.0 - 0.15 * (gx + gy), 0.4, 1.2)
    return np.where(hit, np.clip(shade * light, 0.05, 1.0), 0.0)


#: The overlay's colours (RGB in [0, 1]) and what each means; the report's legend reads them too.
OVERLAY_COLOURS = {
    "both": ((0.3, 0.8, 0.3), "mask and reconstruction"),
    "mask_only": ((0.9, 0.3, 0.3), "mask only"),
    "recon_only": ((0.3, 0.4, 0.9), "reconstruction only"),
}


def project_silhouette(shape: tuple[int, int], occupancy: np.ndarray, voxel_to_camera: np.ndarray) -> np.ndarray:
    """``(h, w)`` bool: the image pixels whose centres the occupied voxels of ``occupancy (D, H, W)``
    cover, each voxel a box of one index step about its centre.

    A grid in its reference camera frame (image x and y each follow one index axis, as every run
    writes them) is projected exactly, by looking each pixel's voxel column up; any other transform
    splats each voxel's centre over its projected footprint, so the silhouette has no holes.

    Example:
        >>> occ = np.zeros((2, 2, 2), bool); occ[0, 1, 1] = True
        >>> T = np.diag([1.0, 3.0, 3.0, 1.0])[[2, 1, 0, 3]]  # (d, h, w) -> (x, y, z) = (3w, 3h, d)
        >>> sil = project_silhouette((6, 6), occ, T)  # the voxel's box: x and y in [1.5, 4.5]
        >>> np.argwhere(sil.any(axis=0)).ravel().tolist(), int(sil.sum())
        ([2, 3, 4], 9)
    """
    h, w = shape
    A, t = np.asarray(voxel_to_camera, dtype=np.float64)[:2, :3], np.asarray(voxel_to_camera, dtype=np.float64)[:2, 3]
    ax, ay = np.flatnonzero(np.abs(A[0]) > 1e-12), np.flatnonzero(np.abs(A[1]) > 1e-12)
    if len(ax) == 1 and len(ay) == 1 and ax[0] != ay[0]:
        foot = occupancy.any(axis=3 - int(ax[0]) - int(ay[0]))
        foot = foot if ay[0] < ax[0] else foot.T  # rows follow image y, columns image x
        iy = np.rint((np.arange(h) - t[1]) / A[1, ay[0]]).astype(np.int64)
        ix = np.rint((np.arange(w) - t[0]) / A[0, ax[0]]).astype(np.int64)
        oky, okx = (iy >= 0) & (iy < foot.shape[0]), (ix >= 0) & (ix < foot.shape[1])
        proj = np.zeros((h, w), dtype=bool)
        proj[np.ix_(oky, okx)] = foot[np.ix_(iy[oky], ix[okx])]
        return proj
    d, hh, ww = np.nonzero(occupancy)
    pts = A @ np.stack([d, hh, ww]).astype(np.float64) + t[:, None]
    proj = np.zeros((h, w), dtype=bool)
    r = int(np.ceil(np.abs(A).max() / 2))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            x = np.round(pts[0] + dx).astype(int)
            y = np.round(pts[1] + dy).astype(int)
            ok = (x >= 0) & (x < w) & (y >= 0) & (y < h)
            proj[y[ok], x[ok]] = True
    return proj


def overlay_colours(mask: np.ndarray, proj: np.ndarray, background: np.ndarray | None = None,
                    alpha: float = 1.0) -> np.ndarray:
    """``(h, w, 3)`` float RGB: ``mask`` and ``proj`` (both ``(h, w)`` bool) in :data:`OVERLAY_COLOURS`,
    blended with weight ``alpha`` over ``background`` (``(h, w, 3)`` in [0, 1]; default white)."""
    rgb = np.ones(mask.shape + (3,)) if background is None else np.array(background, dtype=np.float64)
    for sel, key in ((mask & proj, "both"), (mask & ~proj, "mask_only"), (~mask & proj, "recon_only")):
        rgb[sel] = (1 - alpha) * rgb[sel] + alpha * np.asarray(OVERLAY_COLOURS[key][0])
    return rgb


def silhouette_overlay(mask: np.ndarray, occupancy: np.ndarray, voxel_to_camera: np.ndarray) -> np.ndarray:
    """RGB overlay of an image mask ``(h, w)`` and the projection of the occupied voxels (image pixels)."""
    return overlay_colours(mask, project_silhouette(mask.shape, occupancy, voxel_to_camera))


def crop_box(mask: np.ndarray, pad: int = 10) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)``: the box around ``mask``'s pixels, ``pad`` pixels wider (the whole image if empty)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return 0, mask.shape[0], 0, mask.shape[1]
    return (max(0, ys.min() - pad), min(mask.shape[0], ys.max() + pad + 1), max(0, xs.min() - pad),
            min(mask.shape[1], xs.max() + pad + 1))


#: Height of one object's row in ``preview.png``, in inches (80 pixels each).
PREVIEW_ROW_INCHES = 2.8


def _picks(out: Path, summary: dict, coco, max_objects: int) -> list[tuple[str, Path, dict]]:
    """Up to ``max_objects`` ``(class, voxels file, annotation)``, spread over the classes: each class's first
    objects in id order (numeric stems by value). A file is matched to its annotation through the stem the run
    gives it (:func:`~carvi_torch.io.layout.object_stem`: string ids too; of ids equal as text the first, as the
    loader keeps it); a file no annotation has is passed over."""
    from .io.coco import object_id
    from .io.layout import object_stem

    by_stem: dict = {}
    for ann in coco.dataset.get("annotations", []):  # in file order: the first of ids equal as text, as the loader
        aid = ann.get("id") if isinstance(ann, dict) else None
        if object_id(aid) is not None:  # the ids the run takes (no null, float or bool)
            by_stem.setdefault(object_stem(aid), ann)
    classes = [c for c in summary.get("classes", {}) if (out / c / "voxels").is_dir()]
    per = max(1, max_objects // max(1, len(classes)))
    picks = []
    for c in classes:
        files = sorted((out / c / "voxels").glob("*.npz"), key=lambda p: int(p.stem) if p.stem.isdigit() else 0)
        picks += [(c, f, by_stem[f.stem]) for f in files if f.stem in by_stem][:per]
    return picks[:max_objects]


def write_preview(out: str | Path, summary: dict, max_objects: int = 8) -> Path | None:
    """Draw up to ``max_objects`` reconstructions (spread over the classes) into ``out/preview.png``, a row of
    ``PREVIEW_ROW_INCHES`` per object; ``None`` (nothing written) when no object of the run is in its data."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pycocotools.coco import COCO

    from .io.outputs import atomic_write

    out = Path(out)
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress lines
        coco = COCO(summary["data"]) if summary.get("data") else None
    picks = [] if coco is None else _picks(out, summary, coco, max_objects)
    if not picks:
        return None
    fig, axes = plt.subplots(len(picks), 4, figsize=(12, PREVIEW_ROW_INCHES * len(picks)), squeeze=False)
    for row, (cls, f, ann) in zip(axes, picks):
        z = np.load(f)
        occ, v2c = z["occupancy"], z["voxel_to_camera"]
        aid = ann["id"]
        mask = coco.annToMask(ann).astype(bool)
        y0, y1, x0, x1 = crop_box(mask)
        row[0].imshow(mask[y0:y1, x0:x1], cmap="gray")
        kp = np.asarray(ann["keypoints"], dtype=float).reshape(-1, 3)
        vis = kp[:, 2] > 1
        row[0].plot(kp[vis, 0] - x0, kp[vis, 1] - y0, "o", ms=4, color="orange")
        row[0].set_title(f"{cls} #{aid}: mask + keypoints", fontsize=9)
        row[1].imshow(silhouette_overlay(mask, occ, v2c)[y0:y1, x0:x1])
        row[1].set_title("reconstruction silhouette", fontsize=9)
        # voxel edge lengths along d, h, w, so the views keep the true proportions
        sd, sh, sw = (float(np.linalg.norm(v2c[:3, i])) for i in range(3))
        row[2].imshow(shaded_view(occ, axis=2).T[:, ::-1] if occ.any() else np.zeros((2, 2)), cmap="viridis",
                      aspect=sh / sd)
        row[2].set_title("side view (turned 90 deg)", fontsize=9)
        row[3].imshow(shaded_view(occ, axis=1) if occ.any() else np.zeros((2, 2)), cmap="viridis", aspect=sd / sw)
        row[3].set_title("view from above", fontsize=9)
        for a in row:
            a.set_xticks([])
            a.set_yticks([])
    fig.tight_layout()
    path = out / "preview.png"
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=80))
    plt.close(fig)
    return path
