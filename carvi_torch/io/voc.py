"""PASCAL VOC input: Berkeley keypoint XML + SBD / VOC instance masks -> COCO keypoint JSON.

The converter behind ``python -m carvi_torch.datasets voc --keypoints DIR [--masks DIR]
--out annotations.json``. CPU-side (XML, ``.mat`` and PNG reading, numpy, scipy,
scikit-image, pycocotools); it runs once per dataset, before any tensor work.

Inputs
------
* ``keypoint_dir``: Berkeley keypoint files (``voc2011_keypoints_Feb2012`` format), one
  object per file, ``<image>_<voc_id>.xml``, searched recursively (a flat folder or one
  folder per class)::

      <annotation>
        <image>2008_000037</image> <voc_id>1</voc_id> <category>aeroplane</category>
        <subcategory>Propeller</subcategory>
        <visible_bounds xmin="47" ymin="157" width="403" height="125"/>
        <keypoints> <keypoint name="NoseTip" visible="1" x="371.44" y="210.92" z="0"/> ... </keypoints>
        <polylinesegments> <segment name="foreground" x="57.57 78.99 ..." y="167.84 ..."/> </polylinesegments>
      </annotation>

* ``masks_dir`` (optional): SBD instance maps ``inst/<image>.mat`` (``GTinst.Segmentation``
  ``(H, W)`` instance indices, ``GTinst.Categories`` VOC class index per instance) or VOC
  ``SegmentationObject/<image>.png`` (palette PNG, pixel value = instance index, 0
  background, 255 void boundary; the class of each instance is read from
  ``SegmentationClass/<image>.png`` beside it when present). ``<image>.mat`` /
  ``<image>.png`` directly in ``masks_dir`` are found too.
* ``annotations_dir`` (optional): VOC records ``<image>.xml`` (or
  ``Annotations/<image>.xml``), for the image size and the object's ``occluded`` /
  ``truncated`` flags.

Coordinates
-----------
Berkeley keypoints, polygons and ``visible_bounds`` are 1-based pixel coordinates, like the
VOC records (on the 165 aeroplanes with PASCAL3D+ boxes, ``visible_bounds`` equal the VOC
boxes exactly and the polygons' extents are centred on them within 0.3 px). The converter
subtracts 1 (``one_based=True``) so that the output follows the package convention: x
right, y down, pixel ``[i, j]`` centred at ``(x=j, y=i)``.

Masks
-----
An instance mask from ``masks_dir`` is used when one matches the object: the box of each
instance mask is compared with the object's box (``visible_bounds``, else the extent of
its visible keypoints and polygon) by IoU, objects and instances of one image are paired
one-to-one by :func:`scipy.optimize.linear_sum_assignment` on the IoU, pairs of different
known classes are forbidden and pairs below ``min_iou`` are dropped. Otherwise the
foreground polygon is rasterised at the image size with an exact pixel-centre test
(:func:`skimage.measure.grid_points_in_poly`: pixel ``[i, j]`` is foreground when the point
``(x=j, y=i)`` is inside the polygon or on its boundary; even-odd rule; several foreground
segments are united).

An instance map is held as the map itself: instance boxes (and class votes) come from one scan of it in
blocks of rows, and an instance's mask is made only for the object it is matched to, one at a time, so memory
stays a few bytes per pixel whatever the number of instances. A map of more than ``MAX_IMAGE_PIXELS`` pixels
(a PNG's is refused from its header, before it is decoded; an SBD ``.mat`` whose compressed parts inflate to
more than such a map in doubles, before scipy inflates them) is not read; nor is one holding more than
``MAX_INSTANCES`` instance values.

Image size: the VOC record's ``<size>`` when given, else the instance-map size, else the
extent of all objects of the image (polygons, visible keypoints, ``visible_bounds``):
``ceil(max) + 1`` in 0-based coordinates. A visible keypoint farther outside its object's
polygons and ``visible_bounds`` than half their larger side is a typing error: it is made not
visible, with a warning (:func:`far_keypoints`), before any size is taken. A size of more than
``MAX_IMAGE_PIXELS`` pixels is no size: a record giving one is warned about and not used.

Skipped objects (reported by file name with the reason, the rest goes on): malformed files,
unknown categories, fewer than 2 visible keypoints, no mask (no polygon and no matching
instance), empty masks, no image size (no record, and an instance map or, without one, an extent beyond
``MAX_IMAGE_PIXELS``: every object of that image, with one warning naming it). An instance map that cannot
be read (or a too-large one when a VOC record gives the size) is a warning, and its image's objects fall
back to their polygons.
"""
from __future__ import annotations

import dataclasses
import math
import re
import struct
import sys
import warnings
import xml.etree.ElementTree as ET
import zlib
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from ..collection import infer_flip_pairs, name_words  # name_words re-exported: the converter's word rule
from ..runtime import os_error_line, watch_interrupts
from .coco import MAX_IMAGE_PIXELS, OUTSIDE_TOLERANCE, far_outside
from .coco import encode_mask as encode_rle
from .outputs import write_json
from .vocmeta import (
    ARTICULATED_CLASSES,
    HEAD_TORSO_CLASSES,
    HEAD_TORSO_WORDS,
    HULL_CLASSES,
    LIMB_WORDS,
    MIN_RIGID_KEYPOINTS,
    RIGGING_WORDS,
    ROTATIONAL_CLASSES,
    SUPERCATEGORY,
    TAIL_BASE_WORDS,
    VOC_CLASSES,
    category_id,
    normalize_class_name,
)

__all__ = [
    "VocFormatError",
    "VocObject",
    "VocRecord",
    "InstanceMasks",
    "InstanceMapTooLarge",
    "MAX_INSTANCES",
    "Report",
    "parse_keypoint_xml",
    "parse_voc_record",
    "far_keypoints",
    "read_sbd_instances",
    "read_voc_instances",
    "find_mask_file",
    "name_words",
    "infer_flip_pairs",
    "rigid_keypoint_indices",
    "category_entry",
    "rasterize_polygons",
    "mask_boxes",
    "box_iou",
    "match_instances",
    "encode_rle",
    "convert",
    "run",
]

#: Fewest visible keypoints an object needs to be converted.
MIN_VISIBLE_KEYPOINTS = 2


class VocFormatError(ValueError):
    """A keypoint, record or mask file that cannot be read.

    Attributes:
        path: the file.
        problem: what is wrong, without the file name.
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


# --------------------------------------------------------------------------- Berkeley XML


@dataclass(frozen=True, eq=False)
class VocObject:
    """One object of a Berkeley keypoint file, in 0-based pixel-centre coordinates.

    Attributes:
        source: the file name, e.g. ``"2008_000037_1.xml"``.
        image: VOC image name, e.g. ``"2008_000037"``.
        voc_id: 1-based index of the object in the image's VOC record.
        category: the category as written in the file (see :func:`normalize_class_name`).
        subcategory: e.g. ``"Propeller"``, or ``None``.
        visible_bounds: ``(xmin, ymin, width, height)`` floats, or ``None``.
        keypoints: name -> ``(x, y, visible)``, in file order.
        polygon: ``(P, 2)`` float64 ``(x, y)`` vertices of the first foreground segment, or ``None``.
        polygons: all foreground segments, each ``(P, 2)`` float64 (the mask is their union).
    """

    source: str
    image: str
    voc_id: int
    category: str
    subcategory: str | None
    visible_bounds: tuple[float, float, float, float] | None
    keypoints: dict[str, tuple[float, float, bool]]
    polygon: np.ndarray | None
    polygons: tuple[np.ndarray, ...] = ()

    @property
    def visible_names(self) -> tuple[str, ...]:
        """Names of the visible keypoints, in file order."""
        return tuple(n for n, (_, _, v) in self.keypoints.items() if v)

    @property
    def num_visible(self) -> int:
        """Number of visible keypoints."""
        return len(self.visible_names)

    def _points(self) -> np.ndarray:
        """``(M, 2)`` visible keypoints and polygon vertices."""
        pts = [np.array([[x, y] for x, y, v in self.keypoints.values() if v], dtype=np.float64).reshape(-1, 2)]
        pts += list(self.polygons)
        return np.concatenate(pts, axis=0)

    def box(self) -> np.ndarray:
        """``(4,)`` float64 box ``[x0, y0, x1, y1]`` (pixel-centre extents) used to match masks.

        ``visible_bounds`` when present, else the extent of the visible keypoints and the
        polygon vertices; all NaN when the object has none of them.
        """
        if self.visible_bounds is not None:
            x, y, w, h = self.visible_bounds
            return np.array([x, y, x + w, y + h], dtype=np.float64)
        pts = self._points()
        if len(pts) == 0:
            return np.full(4, np.nan)
        return np.concatenate([pts.min(0), pts.max(0)])

    def extent(self) -> tuple[float, float]:
        """Largest ``(x, y)`` over the polygon, visible keypoints and ``visible_bounds``; NaN if none."""
        pts = self._points()
        if self.visible_bounds is not None:
            x, y, w, h = self.visible_bounds
            pts = np.concatenate([pts, [[x + w, y + h]]], axis=0)
        if len(pts) == 0:
            return (math.nan, math.nan)
        m = pts.max(0)
        return (float(m[0]), float(m[1]))


def _float(path: Path, value: str | None, what: str) -> float:
    if value is None:
        raise VocFormatError(path, f"missing {what}")
    try:
        v = float(value)
    except ValueError:
        raise VocFormatError(path, f"{what} is not a number: {value!r}") from None
    if not math.isfinite(v):
        raise VocFormatError(path, f"{what} is not finite: {value!r}")
    return v


def _text(path: Path, root: ET.Element, tag: str, required: bool = True) -> str | None:
    el = root.find(tag)
    text = el.text.strip() if el is not None and el.text is not None else ""
    if not text:
        if required:
            raise VocFormatError(path, f"missing <{tag}>")
        return None
    return text


def _read_xml(path: Path) -> ET.Element:
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as e:
        line, col = e.position
        msg = str(e).rsplit(": line", 1)[0]
        raise VocFormatError(path, f"malformed XML at line {line}, column {col}: {msg}") from None
    except OSError as e:
        raise VocFormatError(path, f"cannot read the file: {os_error_line(e, said=path)}") from None


def _coordinate_list(path: Path, text: str | None, what: str) -> np.ndarray:
    if text is None:
        raise VocFormatError(path, f"missing {what}")
    try:
        arr = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise VocFormatError(path, f"{what} holds something that is not a number") from None
    if not np.isfinite(arr).all():
        raise VocFormatError(path, f"{what} holds a non-finite value")
    return arr


def parse_keypoint_xml(path: str | Path, *, one_based: bool = True) -> VocObject:
    """Read one Berkeley keypoint file.

    Required: ``<image>``, ``<voc_id>`` (integer), ``<category>``, ``<keypoints>`` (may be
    empty) whose ``<keypoint>`` elements carry ``name``, ``visible``, ``x``, ``y``.
    Optional: ``<subcategory>``, ``<visible_bounds>``, ``<polylinesegments>`` with
    ``<segment name="foreground" x=".." y="..">`` (other segment names are ignored).

    Args:
        path: the ``.xml`` file.
        one_based: the file's coordinates are 1-based (Berkeley / VOC); 1 is subtracted
            from keypoints, polygon and ``visible_bounds`` so that the result uses 0-based
            pixel centres. ``False`` keeps them as written.

    Returns:
        :class:`VocObject`; ``visible`` is ``True`` for a non-zero ``visible`` attribute.

    Raises:
        VocFormatError: malformed XML (with line and column), a missing or non-numeric
            field, a duplicate keypoint name, a polygon with unequal x/y counts or fewer
            than 3 vertices. The message names the file.

    Example:
        >>> obj = parse_keypoint_xml("2008_000037_1.xml")   # doctest: +SKIP
        >>> obj.keypoints["NoseTip"]                        # doctest: +SKIP
        (370.44, 209.92, True)
    """
    path = Path(path)
    root = _read_xml(path)
    if root.tag != "annotation":
        raise VocFormatError(path, f"root element is <{root.tag}>, expected <annotation>")
    off = 1.0 if one_based else 0.0
    image = _text(path, root, "image")
    voc_text = _text(path, root, "voc_id")
    try:
        voc_id = int(voc_text)
    except ValueError:
        raise VocFormatError(path, f"<voc_id> is not an integer: {voc_text!r}") from None
    category = _text(path, root, "category")
    subcategory = _text(path, root, "subcategory", required=False)

    bounds = None
    vb = root.find("visible_bounds")
    if vb is not None:
        vals = [_float(path, vb.get(k), f"visible_bounds {k}") for k in ("xmin", "ymin", "width", "height")]
        bounds = (vals[0] - off, vals[1] - off, vals[2], vals[3])

    kps_el = root.find("keypoints")
    if kps_el is None:
        raise VocFormatError(path, "missing <keypoints>")
    keypoints: dict[str, tuple[float, float, bool]] = {}
    for i, kp in enumerate(kps_el.findall("keypoint")):
        name = (kp.get("name") or "").strip()
        if not name:
            raise VocFormatError(path, f"keypoint {i} has no name")
        if name in keypoints:
            raise VocFormatError(path, f"keypoint {name!r} appears twice")
        x = _float(path, kp.get("x"), f"x of keypoint {name!r}")
        y = _float(path, kp.get("y"), f"y of keypoint {name!r}")
        vis = _float(path, kp.get("visible"), f"visible of keypoint {name!r}")
        keypoints[name] = (x - off, y - off, vis != 0)

    polygons = []
    for seg in root.findall("polylinesegments/segment"):
        if (seg.get("name") or "").strip().lower() != "foreground":
            continue
        xs = _coordinate_list(path, seg.get("x"), "polygon x")
        ys = _coordinate_list(path, seg.get("y"), "polygon y")
        if len(xs) != len(ys):
            raise VocFormatError(path, f"polygon has {len(xs)} x and {len(ys)} y values")
        if len(xs) < 3:
            raise VocFormatError(path, f"polygon has {len(xs)} vertices, needs at least 3")
        polygons.append(np.stack([xs, ys], axis=1) - off)

    return VocObject(source=path.name, image=image, voc_id=voc_id, category=category, subcategory=subcategory,
                     visible_bounds=bounds, keypoints=keypoints, polygon=polygons[0] if polygons else None,
                     polygons=tuple(polygons))


# --------------------------------------------------------------------------- VOC records


@dataclass(frozen=True)
class VocRecord:
    """The parts of a VOC annotation record (``Annotations/<image>.xml``) the converter uses.

    Attributes:
        width, height: image size in pixels.
        objects: per object, in record order (``voc_id - 1``): ``{"name", "truncated",
            "occluded", "difficult"}`` (flags as bool, absent flags false).
    """

    width: int
    height: int
    objects: tuple[dict, ...]


def parse_voc_record(path: str | Path) -> VocRecord:
    """Read a VOC annotation record.

    Raises:
        VocFormatError: malformed XML, missing or non-positive ``<size>``.
    """
    path = Path(path)
    root = _read_xml(path)
    size = root.find("size")
    if size is None:
        raise VocFormatError(path, "missing <size>")
    w = _float(path, _text(path, size, "width"), "size width")
    h = _float(path, _text(path, size, "height"), "size height")
    if w < 1 or h < 1 or w != int(w) or h != int(h):
        raise VocFormatError(path, f"size {w:g}x{h:g} is not a positive integer size")
    if w * h > MAX_IMAGE_PIXELS:
        raise VocFormatError(path, f"size {w:g}x{h:g} is more than {MAX_IMAGE_PIXELS} pixels")

    def flag(el: ET.Element, tag: str) -> bool:
        t = el.findtext(tag)
        try:
            return bool(int(float(t))) if t is not None and t.strip() else False
        except (ValueError, OverflowError):  # OverflowError: "inf"
            raise VocFormatError(path, f"<{tag}> is not 0/1: {t!r}") from None

    objects = tuple({"name": (o.findtext("name") or "").strip(), "truncated": flag(o, "truncated"),
                     "occluded": flag(o, "occluded"), "difficult": flag(o, "difficult")}
                    for o in root.findall("object"))
    return VocRecord(width=int(w), height=int(h), objects=objects)


# --------------------------------------------------------------------------- instance masks

#: Most distinct instance values in one instance map (a 16-bit index's worth); a map holding more is no
#: instance map (its per-instance boxes and class votes alone would not fit in memory).
MAX_INSTANCES = 65535
#: Pixels of an instance map scanned at once (whole rows): what bounds the scan's temporary arrays.
_SCAN_PIXELS = 1 << 15
#: Most bytes the compressed variables of an SBD ``.mat`` may inflate to: a map of ``MAX_IMAGE_PIXELS``
#: pixels stored as doubles.
_MAX_MAT_BYTES = 8 * MAX_IMAGE_PIXELS


class InstanceMapTooLarge(VocFormatError):
    """An instance map (or the file holding it) of more than ``MAX_IMAGE_PIXELS`` pixels, refused before it is
    decoded where the file says its size first (PNG).

    Attributes:
        size: ``(W, H)`` of the map; ``None`` when only the file's decompressed size is known (``.mat``).
    """

    def __init__(self, path: str | Path, size: tuple[int, int] | None, problem: str | None = None):
        self.size = size
        super().__init__(path, problem or f"instance map is {size[0]}x{size[1]} pixels, more than "
                                          f"{MAX_IMAGE_PIXELS}")


@dataclass(frozen=True, eq=False)
class InstanceMasks:
    """The instances of one image's instance map, kept as the map itself: one instance's mask is made when
    asked for (:meth:`mask`), never all of them at once.

    Attributes:
        index_map: ``(H, W)`` integer instance values as the file holds them.
        categories: ``(B,)`` int64 VOC class index (1..20), 0 when unknown.
        ids: ``(B,)`` int64 instance values present in the map, ascending (0 and 255 excluded).
        boxes: ``(B, 4)`` float64 pixel-centre boxes ``[x0, y0, x1, y1]`` of the instances (as
            :func:`mask_boxes`).
        source: ``"sbd"`` or ``"voc"``.
        path: the file read.
    """

    index_map: np.ndarray
    categories: np.ndarray
    ids: np.ndarray
    boxes: np.ndarray
    source: str
    path: Path

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(self.index_map.shape)

    def mask(self, j: int) -> np.ndarray:
        """``(H, W)`` bool mask of instance ``j`` (index into :attr:`ids`), Fortran-ordered as COCO RLE encodes
        it; only its box of the map is compared."""
        x0, y0, x1, y1 = (int(v) for v in self.boxes[j])
        out = np.zeros(self.shape, dtype=bool, order="F")
        crop = self.index_map[y0:y1 + 1, x0:x1 + 1]
        np.equal(crop, crop.dtype.type(self.ids[j]), out=out[y0:y1 + 1, x0:x1 + 1])
        return out


def _row_blocks(height: int, width: int):
    """``(r0, r1)`` row ranges of about ``_SCAN_PIXELS`` pixels covering ``height`` rows."""
    step = max(1, _SCAN_PIXELS // max(width, 1))
    return ((r, min(r + step, height)) for r in range(0, height, step))


def _instance_ids(path: Path, inst_map: np.ndarray) -> np.ndarray:
    """The instance values of an ``(H, W)`` map (excluding 0 and 255), ascending, found block by block;
    :class:`VocFormatError` past ``MAX_INSTANCES``."""
    ids = np.zeros(0, dtype=inst_map.dtype)
    for r0, r1 in _row_blocks(*inst_map.shape):
        ids = np.union1d(ids, inst_map[r0:r1])
        if len(ids) > MAX_INSTANCES + 2:
            break
    ids = ids[(ids != 0) & (ids != 255)]
    if len(ids) > MAX_INSTANCES:
        raise VocFormatError(path, f"holds more than {MAX_INSTANCES} instance values: not an instance map")
    return ids


def _scan_instances(inst_map: np.ndarray, ids: np.ndarray, cls_map: np.ndarray | None = None):
    """Boxes ``(B, 4)`` float64 of the instances ``ids`` of an ``(H, W)`` map and, with an ``(H, W)`` class
    map, votes ``(B, 21)`` int64 (pixels of instance ``b`` with class ``c``, 1..20; 0 for any other value),
    in one pass of row blocks: no array of more than a block's pixels besides the maps."""
    n = len(ids)
    lo = np.full((n, 2), np.iinfo(np.int64).max, dtype=np.int64)  # per instance: min x, min y
    hi = np.full((n, 2), -1, dtype=np.int64)
    votes = np.zeros((n, len(VOC_CLASSES) + 1), dtype=np.int64) if cls_map is not None else None
    for r0, r1 in _row_blocks(*inst_map.shape) if n else ():
        block = inst_map[r0:r1]
        k = np.minimum(np.searchsorted(ids, block), n - 1)
        yy, xx = np.nonzero(ids[k] == block)
        kk = k[yy, xx]
        for axis, v in ((0, xx), (1, yy + r0)):
            np.minimum.at(lo[:, axis], kk, v)
            np.maximum.at(hi[:, axis], kk, v)
        if votes is not None:
            c = cls_map[r0:r1][yy, xx]
            np.add.at(votes, (kk, np.where((c >= 1) & (c <= len(VOC_CLASSES)), c, 0)), 1)
    return np.concatenate([lo, hi], axis=1).astype(np.float64), votes


def _check_mat_size(path: Path) -> None:
    """:class:`InstanceMapTooLarge` when the compressed variables of a MAT-file (v5) inflate to more than
    ``_MAX_MAT_BYTES`` (a map of more than ``MAX_IMAGE_PIXELS`` pixels, or a decompression bomb: kilobytes that
    inflate to gigabytes), measured by inflating them a megabyte at a time; other files pass (scipy reads them)."""
    with open(path, "rb") as f:
        head = f.read(128)
        order = {b"IM": "<", b"MI": ">"}.get(head[126:128])
        if len(head) < 128 or order is None or struct.unpack(order + "H", head[124:126])[0] != 0x0100:
            return
        total = 0
        while len(tag := f.read(8)) == 8:
            mtype, nbytes = struct.unpack(order + "II", tag)
            if mtype != 15:  # not miCOMPRESSED (its bytes are in the file), or a small element (in its tag)
                f.seek(0 if mtype >> 16 else nbytes, 1)
                continue
            inflate, left = zlib.decompressobj(), nbytes
            while left > 0 and (chunk := f.read(min(left, 1 << 20))):
                left -= len(chunk)
                try:
                    while chunk and total <= _MAX_MAT_BYTES:
                        total += len(inflate.decompress(chunk, 1 << 20))
                        chunk = inflate.unconsumed_tail
                except zlib.error:
                    return  # not this check's to judge: scipy says what is wrong
                if total > _MAX_MAT_BYTES:
                    raise InstanceMapTooLarge(path, None, f"inflates to more than {_MAX_MAT_BYTES} bytes, more than "
                                                          f"an instance map of {MAX_IMAGE_PIXELS} pixels")


def read_sbd_instances(path: str | Path) -> InstanceMasks:
    """Read an SBD instance map ``inst/<image>.mat`` (``scipy.io.loadmat``).

    ``GTinst.Segmentation`` is ``(H, W)`` with 0 background and ``k`` on instance ``k``;
    ``GTinst.Categories[k - 1]`` is its VOC class index (1..20).

    Raises:
        InstanceMapTooLarge: a map of more than ``MAX_IMAGE_PIXELS`` pixels, or a file whose compressed parts
            inflate to more than such a map in doubles (checked before scipy inflates them).
        VocFormatError: unreadable file (one that claims more memory than there is, too), no
            ``GTinst``/``Segmentation``, not 2-D, more than ``MAX_INSTANCES`` instances.
    """
    from scipy.io import loadmat
    from scipy.io.matlab import MatReadError

    path = Path(path)
    try:
        _check_mat_size(path)
        mat = loadmat(str(path), squeeze_me=True, struct_as_record=False)
    except (MatReadError, OSError, ValueError, TypeError, IndexError, KeyError, EOFError, NotImplementedError,
            zlib.error, struct.error, MemoryError) as e:  # what scipy raises for corrupt files (an interrupt passes)
        if isinstance(e, VocFormatError):
            raise
        why = "it declares a size beyond memory" if isinstance(e, MemoryError) else e
        raise VocFormatError(path, f"cannot read the .mat file: {why}") from None
    seg = _sbd_segmentation(path, mat)
    cats = getattr(mat["GTinst"], "Categories", None)
    cats = np.atleast_1d(np.asarray(cats if cats is not None else [], dtype=np.float64)).ravel().astype(np.int64)
    cats = np.where((cats >= 1) & (cats <= len(VOC_CLASSES)), cats, 0)
    ids = _instance_ids(path, seg)
    boxes, _ = _scan_instances(seg, ids)
    known = (ids >= 1) & (ids <= len(cats))
    categories = np.zeros(len(ids), dtype=np.int64)
    categories[known] = cats[ids[known].astype(np.int64) - 1]
    return InstanceMasks(index_map=seg, categories=categories, ids=ids.astype(np.int64), boxes=boxes, source="sbd",
                         path=path)


def _sbd_segmentation(path: Path, mat: dict) -> np.ndarray:
    """``GTinst.Segmentation`` as an ``(H, W)`` integer map (its own integer type, else int64)."""
    gt = mat.get("GTinst")
    if gt is None:
        raise VocFormatError(path, "no GTinst structure")
    seg = getattr(gt, "Segmentation", None)
    if seg is None:
        raise VocFormatError(path, "GTinst has no Segmentation")
    seg = np.asarray(seg)
    if seg.ndim != 2 or seg.size == 0:
        raise VocFormatError(path, f"GTinst.Segmentation has shape {seg.shape}, expected (H, W)")
    if seg.size > MAX_IMAGE_PIXELS:
        raise InstanceMapTooLarge(path, (seg.shape[1], seg.shape[0]))
    return seg if seg.dtype.kind in "iu" else seg.astype(np.int64)


def _png_size(path: Path) -> tuple[int, int] | None:
    """``(W, H)`` from a PNG file's header (``IHDR``), read without decoding; ``None`` for another file."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None  # Pillow says what is wrong
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", head[16:24])
    return w, h


def _read_index_png(path: Path, shape: tuple[int, int] | None = None, what: str = "instance map") -> np.ndarray:
    """The ``(H, W)`` index image of a palette or grey-level PNG, in its own integer type. Its size (and, with
    ``shape``, that it is ``shape``) is checked before it is decoded."""
    from PIL import Image

    size = _png_size(path)
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:  # before Pillow, whose own bound is lower
        raise InstanceMapTooLarge(path, size)
    bad_png = (OSError, ValueError, SyntaxError, EOFError, zlib.error, Image.DecompressionBombError)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # MAX_IMAGE_PIXELS is the bound
            with Image.open(path) as im:
                size = im.size
                if size[0] * size[1] > MAX_IMAGE_PIXELS:
                    raise InstanceMapTooLarge(path, size)
                if shape is not None and (size[1], size[0]) != tuple(shape):
                    raise VocFormatError(path, f"{what} {(size[1], size[0])} differs from instance map {tuple(shape)}")
                if im.mode not in ("P", "L", "I", "I;16"):
                    raise VocFormatError(path, f"PNG mode {im.mode!r}: expected a palette or grey-level index image")
                return np.array(im)
    except bad_png as e:  # what Pillow raises for corrupt files (an interrupt passes)
        if isinstance(e, VocFormatError):
            raise
        raise VocFormatError(path, f"cannot read the PNG: {e}") from None


def read_voc_instances(path: str | Path, class_path: str | Path | None = None) -> InstanceMasks:
    """Read a VOC ``SegmentationObject/<image>.png`` (palette index = instance, 255 = void).

    Args:
        path: the instance PNG.
        class_path: ``SegmentationClass/<image>.png`` of the same image, or ``None``. When
            given, each instance's class is the most frequent class index (1..20) under
            its pixels; otherwise classes are unknown (0).

    Raises:
        InstanceMapTooLarge: a map of more than ``MAX_IMAGE_PIXELS`` pixels (refused before it is decoded).
        VocFormatError: unreadable PNG, RGB image, class map of another size, more than ``MAX_INSTANCES``
            instances.
    """
    path = Path(path)
    inst_map = _read_index_png(path)
    ids = _instance_ids(path, inst_map)
    cls_map = None
    if class_path is not None and len(ids):
        cls_map = _read_index_png(Path(class_path), inst_map.shape, "class map")
    boxes, votes = _scan_instances(inst_map, ids, cls_map)
    cats = np.zeros(len(ids), dtype=np.int64)
    if votes is not None:
        votes[:, 0] = 0
        cats = np.where(votes.max(1) > 0, votes.argmax(1), 0)
    return InstanceMasks(index_map=inst_map, categories=cats, ids=ids.astype(np.int64), boxes=boxes, source="voc",
                         path=path)


def find_mask_file(masks_dir: str | Path, image: str) -> tuple[Path, Path | None] | None:
    """The instance-map file of ``image`` under ``masks_dir``, and its class map.

    Looks for ``inst/<image>.mat``, ``<image>.mat``, ``SegmentationObject/<image>.png``,
    ``<image>.png`` in that order. For a PNG, the class map is
    ``SegmentationClass/<image>.png`` beside the ``SegmentationObject`` folder or under
    ``masks_dir`` (``None`` when absent; always ``None`` for ``.mat``).

    Returns:
        ``(instance_file, class_file_or_None)``, or ``None`` when there is no file.
    """
    d = Path(masks_dir)
    for p in (d / "inst" / f"{image}.mat", d / f"{image}.mat"):
        if p.is_file():
            return p, None
    for p in (d / "SegmentationObject" / f"{image}.png", d / f"{image}.png"):
        if p.is_file():
            for c in (p.parent.parent / "SegmentationClass" / p.name, d / "SegmentationClass" / p.name):
                if c.is_file() and c != p:
                    return p, c
            return p, None
    return None


def _read_instances(masks_dir: Path, image: str) -> InstanceMasks | None:
    found = find_mask_file(masks_dir, image)
    if found is None:
        return None
    inst, cls = found
    return read_sbd_instances(inst) if inst.suffix == ".mat" else read_voc_instances(inst, cls)


# --------------------------------------------------------------------------- boxes and matching


def mask_boxes(masks: np.ndarray) -> np.ndarray:
    """Pixel-centre boxes of masks.

    Args:
        masks: ``(B, H, W)`` bool.

    Returns:
        ``(B, 4)`` float64 ``[x0, y0, x1, y1]`` = (first column, first row, last column,
        last row) holding foreground; NaN rows for empty masks.

    Example:
        >>> m = np.zeros((1, 5, 6), bool); m[0, 1:3, 2:5] = True
        >>> mask_boxes(m).tolist()
        [[2.0, 1.0, 4.0, 2.0]]
    """
    masks = np.asarray(masks, dtype=bool)
    if masks.ndim != 3:
        raise ValueError(f"masks: expected (B, H, W), got shape {masks.shape}")
    _, h, w = masks.shape
    rows, cols = masks.any(2), masks.any(1)
    boxes = np.stack([cols.argmax(1), rows.argmax(1), w - 1 - cols[:, ::-1].argmax(1),
                      h - 1 - rows[:, ::-1].argmax(1)], axis=1).astype(np.float64)
    boxes[~rows.any(1)] = np.nan
    return boxes


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of pixel-centre boxes, all pairs.

    A box ``[x0, y0, x1, y1]`` covers the pixels whose centres lie in it, so its area is
    ``(x1 - x0 + 1) * (y1 - y0 + 1)`` (exact for integer boxes).

    Args:
        a: ``(A, 4)``; b: ``(B, 4)`` float. NaN boxes have IoU 0 with everything.

    Returns:
        ``(A, B)`` float64 in ``[0, 1]``.

    Example:
        >>> box_iou(np.array([[0, 0, 1, 1.]]), np.array([[0, 0, 3, 1.]])).tolist()
        [[0.5]]
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    area_a = np.clip(a[:, 2] - a[:, 0] + 1, 0, None) * np.clip(a[:, 3] - a[:, 1] + 1, 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0] + 1, 0, None) * np.clip(b[:, 3] - b[:, 1] + 1, 0, None)
    iw = np.clip(np.minimum(a[:, None, 2], b[None, :, 2]) - np.maximum(a[:, None, 0], b[None, :, 0]) + 1, 0, None)
    ih = np.clip(np.minimum(a[:, None, 3], b[None, :, 3]) - np.maximum(a[:, None, 1], b[None, :, 1]) + 1, 0, None)
    inter = iw * ih
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = inter / (area_a[:, None] + area_b[None, :] - inter)
    return np.nan_to_num(iou, nan=0.0, posinf=0.0, neginf=0.0)


def match_instances(object_boxes: np.ndarray, object_classes: np.ndarray, instance_boxes: np.ndarray,
                    instance_classes: np.ndarray, min_iou: float = 0.5) -> np.ndarray:
    """One-to-one assignment of objects to instance masks by box IoU.

    Maximises the summed IoU (:func:`scipy.optimize.linear_sum_assignment`) over pairs
    that are class-consistent (equal classes, or either unknown = 0) and overlap by at
    least ``min_iou``.

    Args:
        object_boxes: ``(A, 4)`` float boxes (see :func:`box_iou`).
        object_classes: ``(A,)`` int VOC class index, 0 unknown.
        instance_boxes: ``(B, 4)``; instance_classes: ``(B,)`` likewise.
        min_iou: smallest IoU of an accepted pair.

    Returns:
        ``(A,)`` int64: the matched instance index per object, -1 when none.
    """
    object_classes = np.asarray(object_classes, dtype=np.int64).reshape(-1)
    instance_classes = np.asarray(instance_classes, dtype=np.int64).reshape(-1)
    iou = box_iou(object_boxes, instance_boxes)
    if iou.shape != (len(object_classes), len(instance_classes)):
        raise ValueError(f"object_classes / instance_classes: lengths {len(object_classes)}, "
                         f"{len(instance_classes)} do not match the boxes {iou.shape}")
    out = np.full(iou.shape[0], -1, dtype=np.int64)
    if iou.size == 0:
        return out
    oc, ic = object_classes[:, None], instance_classes[None, :]
    ok = ((oc == 0) | (ic == 0) | (oc == ic)) & (iou >= min_iou)
    score = np.where(ok, iou, 0.0)
    from scipy.optimize import linear_sum_assignment

    rows, cols = linear_sum_assignment(score, maximize=True)
    keep = ok[rows, cols]
    out[rows[keep]] = cols[keep]
    return out


# --------------------------------------------------------------------------- rasterising, RLE


def rasterize_polygons(polygons: Sequence[np.ndarray], height: int, width: int) -> np.ndarray:
    """Union of polygons as an ``(H, W)`` bool mask, by an exact pixel-centre test.

    Pixel ``[i, j]`` is set when the point ``(x=j, y=i)`` is inside a polygon or on its
    boundary (even-odd rule within a polygon; skimage's ``grid_points_in_poly``, run on
    each polygon's bounding window). Parts outside the image are clipped.

    Args:
        polygons: each ``(P, 2)`` float ``(x, y)`` vertices, 0-based pixel coordinates.
        height, width: mask size.

    Returns:
        ``(height, width)`` bool.

    Example:
        >>> sq = np.array([[1, 1], [3, 1], [3, 2], [1, 2]], float)
        >>> int(rasterize_polygons([sq], 4, 5).sum())
        6
    """
    from skimage.measure import grid_points_in_poly

    if height < 1 or width < 1:
        raise ValueError(f"height, width: expected positive sizes, got {height}x{width}")
    mask = np.zeros((int(height), int(width)), dtype=bool)
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.float64)
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3:
            raise ValueError(f"polygons: expected (P >= 3, 2) vertices, got shape {poly.shape}")
        x0 = max(0, math.ceil(poly[:, 0].min()))
        y0 = max(0, math.ceil(poly[:, 1].min()))
        x1 = min(width - 1, math.floor(poly[:, 0].max()))
        y1 = min(height - 1, math.floor(poly[:, 1].max()))
        if x0 > x1 or y0 > y1:
            continue
        verts = np.stack([poly[:, 1] - y0, poly[:, 0] - x0], axis=1)  # (row, col)
        mask[y0:y1 + 1, x0:x1 + 1] |= grid_points_in_poly((y1 - y0 + 1, x1 - x0 + 1), verts)
    return mask


# --------------------------------------------------------------------------- names


def _is_head_or_torso(words: list[str]) -> bool:
    ws = set(words)
    if ws & LIMB_WORDS:
        return False
    return bool(ws & HEAD_TORSO_WORDS) or ("tail" in ws and bool(ws & TAIL_BASE_WORDS))


def rigid_keypoint_indices(category: str, names: Sequence[str]) -> list[int]:
    """Indices of the keypoints used by rigid SfM for a class.

    Head/torso classes (animals, person) keep head and torso names, boats keep the hull
    (no sail / mast names), other classes keep everything; the patterns are documented
    in :mod:`carvi_torch.io.vocmeta`. If a pattern keeps fewer than
    ``MIN_RIGID_KEYPOINTS`` names, all indices are returned.

    Args:
        category: class name (normalised with :func:`normalize_class_name`; unknown
            classes keep everything).
        names: ``K`` keypoint names.

    Returns:
        Sorted indices into ``names``.

    Example:
        >>> rigid_keypoint_indices("boat", ["Hull_Back_Bot", "Hull_Back_Top", "Hull_Front_Bot",
        ...                                 "Hull_Front_Top", "Mast_Top", "Sail_Left"])
        [0, 1, 2, 3]
    """
    cls = normalize_class_name(category)
    words = [name_words(n) for n in names]
    if cls in HEAD_TORSO_CLASSES:
        keep = [i for i, w in enumerate(words) if _is_head_or_torso(w)]
    elif cls in HULL_CLASSES:
        keep = [i for i, w in enumerate(words) if not set(w) & RIGGING_WORDS]
    else:
        keep = list(range(len(names)))
    if len(keep) < MIN_RIGID_KEYPOINTS:
        keep = list(range(len(names)))
    return keep


def category_entry(category: str, names: Sequence[str]) -> dict:
    """The COCO category of a VOC class with its carvi extras.

    Args:
        category: VOC class (normalised with :func:`normalize_class_name`).
        names: the class's keypoint names, in output order.

    Returns:
        ``{id, name, supercategory, keypoints, skeleton: [], flip_pairs, rigid_keypoints,
        symmetry, articulated}``; ``id`` is the VOC class index (1..20).

    Raises:
        ValueError: ``category`` is not a VOC class.
    """
    cls = normalize_class_name(category)
    cid = category_id(category)
    names = list(names)
    return {
        "id": cid,
        "name": cls,
        "supercategory": SUPERCATEGORY[cls],
        "keypoints": names,
        "skeleton": [],
        "flip_pairs": [list(p) for p in infer_flip_pairs(names)],
        "rigid_keypoints": rigid_keypoint_indices(cls, names),
        "symmetry": "rotational" if cls in ROTATIONAL_CLASSES else "none",
        "articulated": cls in ARTICULATED_CLASSES,
    }


# --------------------------------------------------------------------------- conversion


@dataclass
class Report:
    """Outcome of :func:`convert`.

    Attributes:
        out_path: the JSON asked for.
        written: whether it was written (not when no object converted).
        counts: converted objects per class.
        skipped: ``(file name, reason)`` per object not converted, sorted by file name.
        excluded: parsed objects of classes not asked for (``classes=``), per class.
        num_files: ``.xml`` files read.
        num_images: images in the output.
        mask_sources: converted objects per mask source (``"polygon"``, ``"sbd"``, ``"voc"``).
        warnings: problems that did not skip an object (an unreadable mask file or VOC
            record: the object falls back to the polygon / the other size sources).
    """

    out_path: Path
    counts: dict[str, int] = field(default_factory=dict)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    excluded: dict[str, int] = field(default_factory=dict)
    num_files: int = 0
    num_images: int = 0
    mask_sources: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    written: bool = False

    @property
    def converted(self) -> int:
        """Total converted objects."""
        return sum(self.counts.values())

    def skipped_by_reason(self) -> dict[str, int]:
        """Skipped objects per kind of reason (the text before the first ``:`` of each reason)."""
        kinds = Counter(" + ".join(r.split(":", 1)[0] for r in reason.split("; ")) for _, reason in self.skipped)
        return dict(sorted(kinds.items()))

    def summary(self, max_files: int = 20) -> str:
        """A short human-readable summary (the full skipped list is in the JSON)."""
        lines = [f"voc: converted {self.converted} objects in {self.num_images} images from "
                 f"{self.num_files} files -> " + (str(self.out_path) if self.written else "nothing written")]
        lines += [f"  {c}: {n}" for c, n in sorted(self.counts.items())]
        if self.mask_sources:
            lines.append("  masks: " + ", ".join(f"{k} {v}" for k, v in sorted(self.mask_sources.items())))
        if self.excluded:
            lines.append("  not asked for: " + ", ".join(f"{c} {n}" for c, n in sorted(self.excluded.items())))
        lines.append(f"skipped {len(self.skipped)}" + (":" if self.skipped else ""))
        lines += [f"  {n} x {k}" for k, n in self.skipped_by_reason().items()]
        lines += [f"    {f}: {r}" for f, r in self.skipped[:max_files]]
        if len(self.skipped) > max_files and self.written:
            lines.append(f"    ... {len(self.skipped) - max_files} more in 'carvi_skipped' of the output")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)


def _check_dir(path: Any, what: str) -> Path | None:
    if path is None:
        return None
    p = Path(path)
    if not p.is_dir():
        raise FileNotFoundError(f"{what}: {p} is not a directory")
    return p


def _wanted_classes(classes: Iterable[str] | str | None) -> set[str] | None:
    if classes is None:
        return None
    if isinstance(classes, str):
        classes = [c for c in re.split(r"[,\s]+", classes) if c]
    wanted, bad = set(), []
    for c in classes:
        n = normalize_class_name(c)
        (bad.append(c) if n is None else wanted.add(n))
    if bad:
        raise ValueError(f"classes: {bad} are not PASCAL VOC classes (one of {', '.join(VOC_CLASSES)})")
    return wanted


def _find_record(annotations_dir: Path, image: str) -> Path | None:
    for p in (annotations_dir / f"{image}.xml", annotations_dir / "Annotations" / f"{image}.xml"):
        if p.is_file():
            return p
    return None


def _extent_size(objs: Sequence[VocObject]) -> tuple[int, int] | str | None:
    """``(W, H)`` spanning the objects (``ceil(max) + 1``), ``None`` without any point, or why it is no size:
    over :data:`~carvi_torch.io.coco.MAX_IMAGE_PIXELS` pixels (a coordinate far off, e.g. ``1e12``)."""
    ext = np.array([o.extent() for o in objs], dtype=np.float64).reshape(-1, 2)
    if np.isnan(ext).all():
        return None
    mx = np.nanmax(ext, axis=0)
    w, h = (max(1.0, math.ceil(v) + 1.0) for v in mx)
    if w * h > MAX_IMAGE_PIXELS:
        return (f"no image size: no VOC record or instance map, and the objects span {w:.0f}x{h:.0f} pixels, "
                f"more than {MAX_IMAGE_PIXELS}")
    return int(w), int(h)


def _round(v: float) -> float:
    return round(float(v), 6)


def convert(keypoint_dir: str | Path, out_path: str | Path, masks_dir: str | Path | None = None,
            annotations_dir: str | Path | None = None, classes: Iterable[str] | str | None = None, *,
            one_based: bool = True, min_iou: float = 0.5) -> Report:
    """Convert Berkeley keypoint files (+ optional SBD / VOC masks) to COCO keypoint JSON.

    See the module docstring for inputs, coordinates, mask matching and image sizes.
    The output (written atomically, and only when an object converts) holds ``info``, ``images`` (``{id, file_name:
    "<image>.jpg", width, height}``, ids by sorted image name), ``annotations`` (ids by
    sorted file path; ``segmentation`` compressed RLE with ``str`` counts, ``area``,
    ``bbox`` from the mask, ``iscrowd`` 0, ``keypoints`` ``[x, y, v] * K`` with ``v = 2``
    for visible keypoints and ``0, 0, 0`` for absent or not visible ones,
    ``num_keypoints``, ``object_id`` (one per ``(image, voc_id)``), ``source`` (the file
    name), ``voc_id``, ``subcategory``, ``mask_source``, ``occluded`` / ``truncated``
    (from the VOC record when ``annotations_dir`` has it, else false)), ``categories`` (one
    per converted class, see :func:`category_entry`; keypoints = sorted union of the names
    of the class's converted objects) and ``carvi_skipped`` (``[{file, reason}]``).

    Args:
        keypoint_dir: folder of Berkeley ``.xml`` files (searched recursively).
        out_path: output JSON path.
        masks_dir: SBD / VOC instance masks (see :func:`find_mask_file`), or ``None``.
        annotations_dir: VOC records, or ``None``.
        classes: VOC classes to convert (names or a comma-separated string); ``None``: all.
            Objects of other classes still take part in mask matching.
        one_based: subtract 1 from the file coordinates (see :func:`parse_keypoint_xml`).
        min_iou: smallest box IoU for an object-instance match.

    Returns:
        :class:`Report`.

    Raises:
        FileNotFoundError: a given folder does not exist.
        ValueError: no ``.xml`` file in ``keypoint_dir``; unknown names in ``classes``, or a class of
            ``classes`` that no parsed file has.
    """
    kdir = _check_dir(keypoint_dir, "keypoint_dir")
    mdir = _check_dir(masks_dir, "masks_dir")
    adir = _check_dir(annotations_dir, "annotations_dir")
    wanted = _wanted_classes(classes)
    files = sorted(kdir.rglob("*.xml"), key=lambda p: p.relative_to(kdir).as_posix())
    if not files:
        raise ValueError(f"keypoint_dir: no .xml files in {kdir}")
    report = Report(out_path=Path(out_path), num_files=len(files))
    excluded: Counter = Counter()
    rank = {p: i for i, p in enumerate(files)}
    with watch_interrupts() as interrupts:  # a Ctrl-C that a reader turned into a bad-file error stops here
        by_image = _parse_files(files, one_based, report)
        interrupts.check()
        _check_classes_present(wanted, by_image, kdir)
        converted = []  # (file, obj, cls, mask_rle, size, mask_source, flags)
        for image in sorted(by_image):
            converted += _convert_image(image, by_image[image], mdir, adir, wanted, min_iou, report, excluded)
            interrupts.check()
    converted.sort(key=lambda c: rank[c[0]])
    categories, images, annotations, counts, sources = _coco_entries(converted)
    report.skipped.sort()
    report.counts = dict(sorted(counts.items()))
    report.excluded = dict(sorted(excluded.items()))
    report.mask_sources = dict(sorted(sources.items()))
    report.num_images = len(images)
    if mdir is not None and annotations and not set(sources) - {"polygon"}:
        report.warnings.append(f"no instance mask under {mdir} matched an object (looked for inst/<image>.mat, "
                               "<image>.mat, SegmentationObject/<image>.png, <image>.png): every mask is the "
                               "XML polygons'")
    data = {
        "info": {"description": "PASCAL VOC Berkeley keypoints converted by carvi_torch.io.voc",
                 "keypoint_dir": str(kdir), "masks_dir": str(mdir) if mdir else None,
                 "annotations_dir": str(adir) if adir else None,
                 "coordinates": "0-based, pixel centres at integers" + (" (file values minus 1)" if one_based else "")},
        "images": images,
        "annotations": annotations,
        "categories": categories,
        "carvi_skipped": [{"file": f, "reason": r} for f, r in report.skipped],
    }
    if annotations:  # nothing converted: nothing written (the report says why)
        write_json(out_path, data)
        report.written = True
    return report


def far_keypoints(obj: VocObject, tolerance: float = OUTSIDE_TOLERANCE) -> tuple[str, ...]:
    """Names of the visible keypoints farther outside the object's own outline (its polygons and
    ``visible_bounds``; none without either) than ``tolerance`` times the outline's larger side: a mistyped
    coordinate, which would otherwise stretch the image size taken from the objects' extent.

    Example:
        >>> sq = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
        >>> o = VocObject("a.xml", "a", 1, "car", None, None, {"x": (12.0, 5.0, True), "y": (2e5, 5.0, True)},
        ...               sq, (sq,))
        >>> far_keypoints(o)
        ('y',)
    """
    pts = list(obj.polygons)
    if obj.visible_bounds is not None:
        x, y, w, h = obj.visible_bounds
        pts.append(np.array([[x, y], [x + w, y + h]]))
    if not pts:
        return ()
    pts = np.concatenate(pts)
    lo, hi = pts.min(0), pts.max(0)
    xy = np.array([(x, y) for x, y, _v in obj.keypoints.values()], dtype=np.float64).reshape(-1, 2)
    far = far_outside(xy, lo, hi, max(float((hi - lo).max()), 1.0), tolerance)
    return tuple(n for (n, (_x, _y, v)), f in zip(obj.keypoints.items(), far) if v and f)


def _check_classes_present(wanted: set[str] | None, by_image: dict, kdir: Path) -> None:
    """``ValueError`` when a class asked for has no object in the parsed files (naming the classes they have)."""
    present = sorted({cls for group in by_image.values() for _, _, cls in group if cls is not None})
    absent = sorted((wanted or set()) - set(present))
    if absent:
        raise ValueError(f"classes: no object of {', '.join(absent)} in the .xml files of {kdir} (their classes: "
                         f"{', '.join(present) or 'none'})")


def _parse_files(files: list[Path], one_based: bool, report: Report) -> dict:
    """Step 1: parse every file; the objects of each image (every parsed object takes part in matching)."""
    by_image: dict[str, list[tuple[Path, VocObject, str | None]]] = defaultdict(list)
    for f in files:
        try:
            obj = parse_keypoint_xml(f, one_based=one_based)
        except VocFormatError as e:
            report.skipped.append((f.name, f"malformed file: {e.problem}"))
            continue
        far = far_keypoints(obj)
        if far:
            report.warnings.append(f"{f.name}: keypoint(s) {', '.join(far)} lie far outside the object's outline; "
                                   "treated as not visible")
            obj = dataclasses.replace(obj, keypoints={n: (x, y, v and n not in far)
                                                      for n, (x, y, v) in obj.keypoints.items()})
        cls = normalize_class_name(obj.category)
        if cls is None:
            report.skipped.append((f.name, f"unknown category: {obj.category!r} is not a PASCAL VOC class"))
        by_image[obj.image].append((f, obj, cls))
    return by_image


def _image_sources(image: str, group: list, mdir, adir, report: Report):
    """The VOC record, the instance masks and the size ``(W, H)`` of one image (any may be ``None``)."""
    record = None
    rec_path = _find_record(adir, image) if adir is not None else None
    if rec_path is not None:
        try:
            record = parse_voc_record(rec_path)
        except VocFormatError as e:
            report.warnings.append(str(e))
    inst, too_large = _instances_of(image, mdir, record is not None, report) if mdir is not None else (None, None)
    if record is not None:
        size = (record.width, record.height)
    elif too_large is not None:
        size = too_large
    elif inst is not None:
        size = (inst.shape[1], inst.shape[0])
    else:
        size = _extent_size([o for _, o, _ in group])
    if isinstance(size, str):
        report.warnings.append(f"{image}: {size}")
    if inst is not None and size is not None and inst.shape != (size[1], size[0]):
        report.warnings.append(f"{inst.path}: instance map is {inst.shape[1]}x{inst.shape[0]}, the VOC record "
                               f"says {size[0]}x{size[1]}; using polygons for {image}")
        inst = None
    return record, inst, size


def _instances_of(image: str, mdir: Path, has_record: bool, report: Report):
    """The image's instance masks (``None``: no map, or one warned about, whose objects fall back to their
    polygons), and why the image has no size when its map is too large and no VOC record gives one."""
    try:
        return _read_instances(mdir, image), None
    except InstanceMapTooLarge as e:
        if not has_record:  # the map gives the image's size, and it is too large: no size
            return None, f"no image size: {e.path.name}: {e.problem}"
        report.warnings.append(f"{e}; using polygons for {image}")
    except VocFormatError as e:
        report.warnings.append(f"{e}; using polygons for {image}")
    return None, None


def _object_mask(obj: VocObject, j: int, inst, size, mdir, reasons: list):
    """The object's mask and its source: the matched instance mask, else its polygons (or a reason)."""
    mask, source = None, None
    if j >= 0:
        mask, source = inst.mask(j), inst.source
    elif isinstance(size, str):
        reasons.append(size)
    elif obj.polygons and size is not None:
        mask, source = rasterize_polygons(obj.polygons, size[1], size[0]), "polygon"
    else:
        looked = " and no matching instance mask" if mdir is not None else ""
        reasons.append(f"no mask: no foreground polygon{looked}")
    if mask is not None and not mask.any():
        reasons.append(f"empty mask: the {source} covers no pixel of the {size[0]}x{size[1]} image")
    return mask, source


def _convert_image(image, group, mdir, adir, wanted, min_iou, report: Report, excluded: Counter) -> list:
    """Step 2: one image's objects matched to its instance masks and converted (or skipped, with reasons)."""
    record, inst, size = _image_sources(image, group, mdir, adir, report)
    match = np.full(len(group), -1, dtype=np.int64)
    if inst is not None and len(inst.ids):
        obj_boxes = np.stack([o.box() for _, o, _ in group])
        obj_cls = np.array([VOC_CLASSES.index(c) + 1 if c else 0 for _, _, c in group], dtype=np.int64)
        match = match_instances(obj_boxes, obj_cls, inst.boxes, inst.categories, min_iou)
    converted = []
    for (f, obj, cls), j in zip(group, match):
        if cls is None:
            continue  # reported at parsing
        if wanted is not None and cls not in wanted:
            excluded[cls] += 1
            continue
        reasons = []
        if obj.num_visible < MIN_VISIBLE_KEYPOINTS:
            reasons.append(f"too few visible keypoints: {obj.num_visible} visible, needs {MIN_VISIBLE_KEYPOINTS}")
        mask, source = _object_mask(obj, j, inst, size, mdir, reasons)
        if reasons:
            report.skipped.append((f.name, "; ".join(reasons)))
            continue
        flags = {"occluded": False, "truncated": False}
        if record is not None and 1 <= obj.voc_id <= len(record.objects):
            rec_obj = record.objects[obj.voc_id - 1]
            flags = {"occluded": rec_obj["occluded"], "truncated": rec_obj["truncated"]}
        converted.append((f, obj, cls, encode_rle(mask), size, source, flags))
    return converted


def _coco_entries(converted: list):
    """Step 3: the COCO categories, images and annotations of the converted objects, and counts per
    class and per mask source."""
    from pycocotools import mask as mask_utils

    names_by_class: dict[str, set[str]] = defaultdict(set)
    for _, obj, cls, *_ in converted:
        names_by_class[cls].update(obj.keypoints)
    categories = [category_entry(c, sorted(names_by_class[c])) for c in VOC_CLASSES if c in names_by_class]
    cat_by_name = {c["name"]: c for c in categories}
    image_sizes = {obj.image: size for _, obj, _, _, size, _, _ in converted}
    image_ids = {im: i + 1 for i, im in enumerate(sorted(image_sizes))}
    object_ids = {k: i + 1 for i, k in enumerate(sorted({(o.image, o.voc_id) for _, o, *_ in converted}))}
    images = [{"id": image_ids[im], "file_name": f"{im}.jpg", "width": int(image_sizes[im][0]),
               "height": int(image_sizes[im][1])} for im in sorted(image_sizes)]
    annotations = []
    counts: Counter = Counter()
    sources: Counter = Counter()
    for ann_id, (f, obj, cls, rle, size, source, flags) in enumerate(converted, start=1):
        kps = []
        for n in cat_by_name[cls]["keypoints"]:
            x, y, v = obj.keypoints.get(n, (0.0, 0.0, False))
            kps += [_round(x), _round(y), 2] if v else [0, 0, 0]
        annotations.append({
            "id": ann_id, "image_id": image_ids[obj.image], "category_id": cat_by_name[cls]["id"],
            "segmentation": rle, "area": float(mask_utils.area(rle)),
            "bbox": [float(v) for v in mask_utils.toBbox(rle)], "iscrowd": 0, "keypoints": kps,
            "num_keypoints": obj.num_visible, "object_id": object_ids[(obj.image, obj.voc_id)],
            "source": obj.source, "voc_id": obj.voc_id, "subcategory": obj.subcategory, "mask_source": source,
            "occluded": bool(flags["occluded"]), "truncated": bool(flags["truncated"]),
        })
        counts[cls] += 1
        sources[source] += 1
    return categories, images, annotations, counts, sources


def run(args: Any) -> int:
    """Command-line entry: ``python -m carvi_torch.datasets voc --keypoints DIR [--masks DIR]
    [--annotations DIR] --out annotations.json``.

    Args:
        args: an object with ``.keypoints``, ``.out`` and optionally ``.masks``,
            ``.annotations``, ``.classes`` (missing attributes count as ``None``).

    Returns:
        0 when at least one object was converted, 1 when none was (nothing is written), 2 on bad
        arguments (a ``--classes`` name that no file has, too) or a missing folder (one ``error:`` line, naming
        the option). Prints :meth:`Report.summary`.
        Another ``OSError`` (an output that cannot be written) is raised: ``datasets``' shared ending prints it
        as one ``error:`` line.
    """
    keypoints, out = getattr(args, "keypoints", None), getattr(args, "out", None)
    if keypoints is None or out is None:
        print("error: voc: --keypoints and --out are required", file=sys.stderr)
        return 2
    try:
        report = convert(keypoints, out, masks_dir=getattr(args, "masks", None),
                         annotations_dir=getattr(args, "annotations", None), classes=getattr(args, "classes", None))
    except (FileNotFoundError, ValueError) as e:
        said = os_error_line(e) if getattr(e, "filename", None) and e.strerror else _option_names(str(e))
        print(f"error: voc: {said}", file=sys.stderr)
        return 2
    print(report.summary(max_files=len(report.skipped) if not report.written else 20))
    if report.converted == 0:
        print("error: voc: no object was converted", file=sys.stderr)
        return 1
    return 0


#: :func:`convert`'s argument names and the command-line options that set them.
_OPTIONS = {"keypoint_dir": "--keypoints", "masks_dir": "--masks", "annotations_dir": "--annotations",
            "classes": "--classes"}


def _option_names(message: str) -> str:
    """A :func:`convert` error as the command line says it: the option instead of the argument name.

    Example:
        >>> _option_names("keypoint_dir: /x is not a directory")
        '--keypoints: /x is not a directory'
    """
    name, sep, rest = message.partition(":")
    return f"{_OPTIONS[name]}{sep}{rest}" if sep and name in _OPTIONS else message
