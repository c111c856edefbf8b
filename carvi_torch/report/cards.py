"""One card per object: the overlay image (JPEG) and the 3D mesh data (a script file) the page loads.

An object's overlay shows its image crop (white where the run has no photo) with the mask and the
reconstruction's silhouette in :data:`carvi_torch.preview.OVERLAY_COLOURS`, the annotated keypoints
and the class mean shape's keypoints projected by the object's camera. Its mesh is decimated to at
most ``max_faces`` faces and written as ``carviReport.mesh(key, data)`` with int16-quantised
positions (:mod:`carvi_torch.report.mesh_data`), so the page can load it from disk (``file://``) by a
script tag; that script may be made in another process (:func:`card_without_mesh`, :func:`add_mesh`).
A missing or damaged file never stops the report: the card lists the reason (``Card.problems``).
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..io.layout import object_mesh
from ..io.outputs import write_within
from ..io.results import annotation_source, same_object
from ..preview import OVERLAY_COLOURS, crop_box, overlay_colours, project_silhouette
from .inputs import ClassInputs, ObjectInputs
from .mesh_data import decode_positions, encode_mesh, write_mesh_script

__all__ = ["Card", "CardContext", "ClassView", "legend", "encode_mesh", "decode_positions", "make_card",
           "card_without_mesh", "add_mesh", "keypoint_residual", "image_path", "KEYPOINT_COLOURS", "CROP_SIZE"]

#: Marker colours (RGB 0-255) of the keypoints on the overlay, and what each means (the legend reads them).
KEYPOINT_COLOURS = {"annotated": ((255, 150, 0), "annotated keypoint"),
                    "projected": ((0, 200, 220), "mean-shape keypoint, projected")}
#: The overlay image's longer side, pixels.
CROP_SIZE = 208


@dataclass
class Card:
    """What the page shows of one object (one entry of ``cards.js``)."""

    id: str
    cls: str
    key: str
    """``<class key>/<stem>``: unique in the run, and the mesh script's registration key."""
    source: str | None = None
    img: str | None = None
    mesh: str | None = None
    files: dict = field(default_factory=dict)
    quality: float | None = None
    score: float | None = None
    iou: float | None = None
    """Intersection over union of the mask and the reconstruction's silhouette."""
    residual_sfm: float | None = None
    residual: float | None = None
    az: float | None = None
    el: float | None = None
    camera_from: str | None = None
    surrogates_from: str | None = None
    skipped: str | None = None
    problems: list = field(default_factory=list)
    faces: int | None = None

    def to_json(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()
                if v is not None and v != [] and v != {}}


def _project(cam: dict | None, shape: np.ndarray) -> np.ndarray | None:
    """``(K, 2)`` image points of ``shape (K, 3)`` under ``cam`` (``uv = s X R[:2]^T + t``), or ``None``."""
    try:
        R, s, t = np.asarray(cam["R"], float), float(cam["s"]), np.asarray(cam["t"], float)
        return s * shape @ R[:2].T + t
    except (TypeError, KeyError, ValueError):
        return None


def keypoint_residual(cam: dict | None, shape: np.ndarray, kp: np.ndarray) -> float | None:
    """Mean image distance (pixels) between the visible keypoints ``kp (K, 3)`` (``x, y, v``; visible:
    ``v >= 2``) and the mean shape ``shape (K, 3)`` projected by ``cam``; ``None`` if none compare.

    Example:
        >>> cam = {"R": np.eye(3).tolist(), "s": 2.0, "t": [1.0, 0.0]}
        >>> keypoint_residual(cam, np.array([[0., 0, 0], [1, 1, 0]]), np.array([[1., 0, 2], [3, 5, 2]]))
        1.5
    """
    uv = _project(cam, shape)
    if uv is None:
        return None
    ok = (kp[:, 2] >= 2) & np.isfinite(uv).all(axis=1) & np.isfinite(kp[:, :2]).all(axis=1)
    return float(np.linalg.norm(uv[ok] - kp[ok, :2], axis=1).mean()) if ok.any() else None


def _draw(mask, proj, photo, kp, uv) -> "Image.Image":  # noqa: F821 - PIL is imported lazily
    """The overlay image: crop around mask and silhouette, scaled to :data:`CROP_SIZE`, keypoints drawn."""
    from PIL import Image, ImageDraw

    y0, y1, x0, x1 = crop_box(mask | proj)
    rgb = overlay_colours(mask[y0:y1, x0:x1], proj[y0:y1, x0:x1],
                          None if photo is None else photo[y0:y1, x0:x1], alpha=1.0 if photo is None else 0.5)
    img = Image.fromarray((np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    k = CROP_SIZE / max(img.size)
    img = img.resize((max(1, round(img.size[0] * k)), max(1, round(img.size[1] * k))), Image.BILINEAR)
    d = ImageDraw.Draw(img)
    for pts, (colour, _), cross in ((uv, KEYPOINT_COLOURS["projected"], True),
                                    (kp, KEYPOINT_COLOURS["annotated"], False)):
        if pts is None:
            continue
        for x, y in (pts[:, :2] - (x0, y0)) * k:
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            if cross:
                d.line([(x - 4, y - 4), (x + 4, y + 4)], fill=colour, width=2)
                d.line([(x - 4, y + 4), (x + 4, y - 4)], fill=colour, width=2)
            else:
                d.ellipse([x - 3, y - 3, x + 3, y + 3], fill=colour, outline=(0, 0, 0))
    return img


def image_path(data: Path, name) -> Path | None:
    """The image file ``name`` (an image entry's ``file_name``) of the annotation file ``data``: relative to
    ``data``'s folder, or to the folder above it (``../images/a.jpg``: images kept beside the annotation
    folder); ``None`` for a name that is not a string, is absolute, or climbs farther (never read).

    Example:
        >>> data = Path("d/ann/a.json")
        >>> image_path(data, "x.jpg").as_posix(), image_path(data, "../img/x.jpg").as_posix()
        ('d/ann/x.jpg', 'd/img/x.jpg')
        >>> image_path(data, "/etc/passwd"), image_path(data, "../../x.jpg")
        (None, None)
    """
    if not isinstance(name, str) or not name or "\0" in name:
        return None
    rel = Path(os.path.normpath(name))
    if rel.is_absolute() or rel.parts.count("..") > 1:  # normpath leaves ".." only at the start
        return None
    return Path(os.path.normpath(data.parent / rel))


def _photo(ctx, ann: dict, shape) -> np.ndarray | None:
    """The object's image as ``(h, w, 3)`` floats in [0, 1], when :func:`image_path` names a regular file
    that is an image of the mask's size; else ``None`` (the overlay is drawn on white)."""
    img = ctx.images.get(ann.get("image_id")) or {}
    path = image_path(ctx.data, img.get("file_name")) if ctx.data is not None else None
    try:
        if path is None or not path.is_file():  # not a folder, a pipe or a device
            return None
        from PIL import Image

        with Image.open(path) as im:
            if im.size != (shape[1], shape[0]):  # another image: not decoded
                return None
            return np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
    except Exception:  # noqa: BLE001 - unreadable or not an image: the overlay is drawn on white
        return None


@dataclass
class CardContext:
    """What every card of a run shares: folders, the annotations and limits."""

    recon: Path
    out: Path
    anns: dict
    """Annotation id (as a string) -> its COCO annotation; empty when the input file is unreadable."""
    images: dict
    coco: object | None
    data: Path | None
    mesh_format: str = "ply"
    max_faces: int = 4000
    jpeg_quality: int = 82
    data_problem: str | None = None
    ann_class: dict = field(default_factory=dict)
    """Annotation id (as a string) -> the class key of its category in the input file (``None``: unknown)."""


@dataclass
class ClassView:
    """What a card needs of its class: the folder key and the mean shapes (per shape group, ``(K, 3)``)."""

    key: str
    mean_shapes: list

    @classmethod
    def of(cls, c: ClassInputs) -> "ClassView":
        return cls(c.key, c.mean_shapes)


def _links(ctx: CardContext, cls: ClassView, obj: ObjectInputs) -> dict:
    """Relative links from the report to the object's files (only those that exist)."""
    from urllib.parse import quote

    cdir = ctx.recon / cls.key
    files = {"mesh": object_mesh(cdir, obj.annotation_id, ctx.mesh_format),
             "voxels": cdir / "voxels" / f"{obj.stem}.npz", "cameras": cdir / "cameras.json"}
    return {k: quote(Path(os.path.relpath(p, ctx.out)).as_posix()) for k, p in files.items()
            if p is not None and p.is_file()}


def _overlay(ctx: CardContext, cls: ClassView, obj: ObjectInputs, card: Card, rel: str) -> None:
    """Mask, silhouette and keypoints of one object into ``ctx.out / rel`` (a JPEG); fills the card's numbers."""
    ann = ctx.anns.get(obj.annotation_id)
    if ann is None:
        card.problems.append(ctx.data_problem or "annotation not in the input file: no overlay")
        return
    now_class, now_source = ctx.ann_class.get(obj.annotation_id), annotation_source(ann)
    if not same_object(cls.key, obj.source, now_class, now_source):  # the file changed since the run
        card.problems.append(f"annotation {obj.annotation_id} is now {now_class} {now_source}, not the run's: "
                             "no overlay")
        return
    try:
        mask = ctx.coco.annToMask(ann).astype(bool)
    except Exception as e:  # noqa: BLE001 - a damaged segmentation: the card says so
        if obj.skipped is None:  # a skipped object's card gives the reason already (at load, often this one)
            card.problems.append(f"mask unreadable ({type(e).__name__}): no overlay")
        return
    proj = np.zeros_like(mask)
    vox = ctx.recon / cls.key / "voxels" / f"{obj.stem}.npz"
    if obj.skipped is None:
        try:
            with np.load(vox) as z:
                proj = project_silhouette(mask.shape, z["occupancy"], z["voxel_to_camera"])
            card.iou = float((mask & proj).sum() / max(1, (mask | proj).sum()))
        except Exception as e:  # noqa: BLE001 - missing or damaged voxels: the overlay shows the mask alone
            card.problems.append(f"voxels {'missing' if not vox.is_file() else 'unreadable'} ({type(e).__name__}): "
                                 "no silhouette")
    kp = np.asarray(ann.get("keypoints") or [], dtype=np.float64).reshape(-1, 3)
    shape = cls.mean_shapes[obj.shape_group] if obj.shape_group < len(cls.mean_shapes) else None
    uv = None
    if shape is not None and len(shape) == len(kp):
        uv = _project(obj.camera, shape)
        card.residual = keypoint_residual(obj.camera, shape, kp)
        card.residual_sfm = keypoint_residual(obj.sfm, shape, kp)
    vis = kp[kp[:, 2] >= 2] if len(kp) else None
    img = _draw(mask, proj, _photo(ctx, ann, mask.shape), vis, uv)
    write_within(ctx.out, rel, lambda f: img.save(f, format="JPEG", quality=ctx.jpeg_quality), sync=False)
    card.img = rel


def _mesh_job(ctx: CardContext, cls: ClassView, obj: ObjectInputs, card: Card, rel: str) -> tuple | None:
    """:func:`~carvi_torch.report.mesh_data.write_mesh_script`'s arguments for the object's decimated mesh (the
    file the export takes: :func:`~carvi_torch.io.layout.object_mesh`) as the script ``ctx.out / rel``; ``None``
    when it has no mesh file (the card says so)."""
    src = object_mesh(ctx.recon / cls.key, obj.annotation_id, ctx.mesh_format)
    if src is None:
        card.problems.append(f"no mesh file ({obj.stem}.{ctx.mesh_format}): no 3D view")
        return None
    return str(src), str(ctx.out), rel, card.key, ctx.max_faces


def add_mesh(card: Card, job: tuple, made: tuple[int | None, str | None]) -> None:
    """Book on ``card`` what :func:`~carvi_torch.report.mesh_data.write_mesh_script` ``(*job)`` returned."""
    faces, problem = made
    if problem is not None:
        card.problems.append(problem)
    else:
        card.mesh, card.faces = job[2], faces


def failed_card(cls: ClassView, obj: ObjectInputs, out_key: str, e: Exception) -> Card:
    """The card of an object whose card could not be made: the reason is its one problem."""
    return Card(id=obj.annotation_id, cls=cls.key, key=f"{out_key}/{obj.stem}", source=obj.source,
                skipped=obj.skipped, problems=[f"card failed ({type(e).__name__}: {str(e)[:120]})"])


def make_card(ctx: CardContext, cls: ClassView, obj: ObjectInputs, out_key: str) -> Card:
    """Write one object's overlay and mesh script under ``ctx.out/objects/<out_key>/`` and return its card;
    whatever goes wrong, the card says so (``problems``) rather than raise."""
    try:
        card, job = _make_card(ctx, cls, obj, out_key)
        if job is not None:
            add_mesh(card, job, write_mesh_script(*job))
        return card
    except Exception as e:  # noqa: BLE001 - one object's failure is its card's reason, never the report's end
        return failed_card(cls, obj, out_key, e)


def card_without_mesh(ctx: CardContext, cls: ClassView, obj: ObjectInputs, out_key: str) -> tuple[Card, tuple | None]:
    """:func:`make_card` but for the mesh script: the card and the arguments of
    :func:`~carvi_torch.report.mesh_data.write_mesh_script` that make it (``None``: none to make), for the caller
    to run where it likes and book with :func:`add_mesh`."""
    try:
        return _make_card(ctx, cls, obj, out_key)
    except Exception as e:  # noqa: BLE001 - one object's failure is its card's reason, never the report's end
        return failed_card(cls, obj, out_key, e), None


def _make_card(ctx: CardContext, cls: ClassView, obj: ObjectInputs, out_key: str) -> tuple[Card, tuple | None]:
    card = Card(id=obj.annotation_id, cls=cls.key, key=f"{out_key}/{obj.stem}", source=obj.source,
                quality=obj.quality, score=obj.score, az=obj.azimuth_deg, el=obj.elevation_deg,
                camera_from=obj.camera_from, surrogates_from=obj.surrogates_from, skipped=obj.skipped)
    card.files = _links(ctx, cls, obj)
    if obj.problem is not None:
        card.problems.append(obj.problem)
    base = f"objects/{out_key}/{obj.stem}"
    _overlay(ctx, cls, obj, card, base + ".jpg")
    return card, (_mesh_job(ctx, cls, obj, card, base + ".js") if obj.skipped is None else None)


def legend() -> list[tuple[str, str, str]]:
    """``(kind, css colour, meaning)`` of every mark on an overlay: ``area`` fills, ``dot``/``cross`` markers."""
    def css(rgb):
        return "#" + "".join(f"{round(c * 255) if isinstance(c, float) else c:02x}" for c in rgb)

    out = [("area", css(c), text) for c, text in OVERLAY_COLOURS.values()]
    out.append(("dot", css(KEYPOINT_COLOURS["annotated"][0]), KEYPOINT_COLOURS["annotated"][1]))
    out.append(("cross", css(KEYPOINT_COLOURS["projected"][0]), KEYPOINT_COLOURS["projected"][1]))
    return out
