"""COCO keypoint JSON in and out, with the carvi extras, validated per object.

Input follows pycocotools conventions: ``keypoints`` is ``[x, y, v] * K`` with
``v = 0`` not labelled, ``1`` labelled but not visible, ``2`` visible;
``segmentation`` is RLE (compressed or not) or polygons. carvi extras on a
category (all optional): ``flip_pairs``, ``rigid_keypoints``, ``symmetry``
(``"none"`` / ``"rotational"``), ``articulated``, ``left_convention`` (``"object"``: a
keypoint named left is on the object's own left, the default; ``"viewer"``: on the left of a
frontal photo, as PASCAL3D+ CAD names); on an annotation: ``occluded``,
``truncated`` (not reconstructed), ``object_id``, ``source``, ``split``.

Validation never stops the run for one bad object: every problem becomes a
:class:`Problem` (object, class, reason) that the pipeline writes to
``summary.json``; only an unreadable file (missing, malformed JSON, no
``annotations`` list) raises :class:`CocoFormatError`.
"""
from __future__ import annotations

import hashlib
import json
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
from pycocotools import mask as mask_utils

from ..cameras import Similarity2D
from ..collection import ClassCollection, ClassMeta, canvas_similarity, infer_flip_pairs, resample_to_canvases
from ..runtime import os_error_line, torch_threads, watch_interrupts
from .layout import object_stem, reserved
from .outputs import numbers, read_json, safe_name, shown, shown_names, write_json

__all__ = ["CocoFormatError", "Problem", "LoadResult", "load_coco", "encode_mask", "decode_segmentation",
           "clip_polygon", "make_category", "make_annotation", "write_coco", "OUTSIDE_TOLERANCE", "far_outside",
           "MAX_IMAGE_PIXELS", "object_id", "flag", "class_keys", "class_names", "select_classes",
           "input_fingerprints", "skipped_at_load", "DUPLICATE_ID", "is_duplicate", "rle_counts", "decode_counts"]

#: How the reason of a repeated annotation id begins (the id's first annotation is the one used).
DUPLICATE_ID = "duplicate annotation id"


def is_duplicate(problem: Problem) -> bool:
    """Whether ``problem`` is a repeated annotation id: its id names the first annotation with that id (the
    object that is used), so a per-object failure keyed by id must leave it out.

    Example:
        >>> is_duplicate(Problem(f"{DUPLICATE_ID} 7; keeping the first", annotation_id=7))
        True
    """
    return problem.reason.startswith(DUPLICATE_ID)


def skipped_at_load(problems: list, key: str) -> list[dict]:
    """The objects of class folder ``key`` that the load skipped (fatal problems naming an annotation), each as
    ``{annotation_id, source, stage, reason}``: what ``summary.json`` books as the class's load failures and the
    export lists as skipped. A repeated annotation id is left out (:func:`is_duplicate`; it stays among the
    problems).

    Example:
        >>> skipped_at_load([Problem("empty mask", annotation_id=3, class_key="car"),
        ...                  Problem(f"{DUPLICATE_ID} 4; keeping the first", annotation_id=4, class_key="car")], "car")
        [{'annotation_id': 3, 'source': None, 'stage': 'load', 'reason': 'empty mask'}]
    """
    return [{"annotation_id": p.annotation_id, "source": p.source, "stage": p.stage, "reason": p.reason}
            for p in problems if p.fatal and p.class_key == key and p.annotation_id is not None
            and not is_duplicate(p)]


#: Keypoints farther outside the image than this fraction of its larger side are rejected.
OUTSIDE_TOLERANCE = 0.5
#: Bound on the magnitude of a category's ``keypoints_3d`` coordinates: a larger one is no template point.
_KEYPOINTS_3D_BOUND = 1e300
#: Default bound on an image's pixels (a mask is decoded at one byte per pixel of its image).
MAX_IMAGE_PIXELS = 200_000_000


def far_outside(xy: np.ndarray, lo, hi, side: float, tolerance: float = OUTSIDE_TOLERANCE) -> np.ndarray:
    """``(N,)`` bool: which points of ``xy`` ``(N, 2)`` float64 lie farther than ``tolerance * side`` outside the
    box ``lo`` to ``hi`` (each ``(x, y)``, bounds inclusive); a NaN coordinate is outside. The one rule of a
    mistyped keypoint, of COCO (the box is the image) and of the VOC converter (the object's outline).

    Example:
        >>> far_outside(np.array([[-4.0, 5.0], [-6.0, 5.0], [9.0, 25.0]]), (0, 0), (9, 9), 10)
        array([False,  True,  True])
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    tol = tolerance * side
    with np.errstate(invalid="ignore"):
        return ~((lo - tol <= xy) & (xy <= hi + tol)).all(axis=-1)


class CocoFormatError(ValueError):
    """The annotation file cannot be read at all (names the file and the problem)."""


@dataclass
class Problem:
    """One object (or class) that could not be used, and why."""

    reason: str
    annotation_id: int | str | None = None
    category: str | None = None
    source: str | None = None
    stage: str = "load"
    fatal: bool = True  # False: a warning, the object is still used
    class_key: str | None = None  # the folder of the object's class (``ClassMeta.key``), where known

    def message(self) -> str:
        who = []
        if self.category:
            who.append(self.category)
        if self.annotation_id is not None:
            who.append(f"annotation {self.annotation_id}")
        if self.source:
            who.append(f"({self.source})")
        kind = "skipped" if self.fatal else "warning"
        return f"[{self.stage}] {' '.join(who) or 'input'}: {self.reason} -> {kind}"

    def to_dict(self) -> dict:
        return {"annotation_id": self.annotation_id, "category": self.category, "source": self.source,
                "stage": self.stage, "reason": self.reason, "skipped": self.fatal}


@dataclass
class LoadResult:
    """Collections per class name, problems found, and the raw dataset."""

    collections: dict
    problems: list = field(default_factory=list)
    dataset: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- masks


def encode_mask(mask: np.ndarray | torch.Tensor) -> dict:
    """Compressed RLE of an ``(H, W)`` bool mask, ``counts`` as str (JSON-ready).

    Example:
        >>> rle = encode_mask(np.ones((2, 3), bool)); rle["size"]
        [2, 3]
    """
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    mask = np.asarray(mask)
    mask = mask.view(np.uint8) if mask.dtype == bool else mask.astype(np.uint8, copy=False)  # a bool mask: no copy
    rle = mask_utils.encode(np.asfortranarray(mask))
    rle["counts"] = rle["counts"].decode("ascii")
    return {"size": [int(v) for v in rle["size"]], "counts": rle["counts"]}


def clip_polygon(flat: np.ndarray, height: int, width: int) -> np.ndarray:
    """A flat ``[x, y] * n`` polygon cut to the box of one image size around the image, ``[-W, 2W] x [-H, 2H]``
    (Sutherland-Hodgman; flat again, possibly fewer than 3 points when nothing is left).

    pycocotools rasterises a polygon edge by edge at five samples per pixel of its length, so one far vertex
    (1e8) costs gigabytes and a farther one (1e12) crashes the process. A polygon inside the box comes back as
    it is (its mask is exactly pycocotools'); a cut one covers the same part of the image, up to the rounding
    of the edges that leave the box. The box's edges lie outside the image, so the cut's edges paint nothing.

    Example:
        >>> clip_polygon(np.array([0., 0., 1e12, 0., 0., 10.]), 10, 10).reshape(-1, 2).max(0).tolist()
        [20.0, 10.0]
    """
    flat = np.asarray(flat, dtype=np.float64)
    pts = flat[:len(flat) // 2 * 2].reshape(-1, 2)  # an odd last value is dropped, as pycocotools does
    box = ((-float(width), 2.0 * width), (-float(height), 2.0 * height))
    if ((pts >= [box[0][0], box[1][0]]) & (pts <= [box[0][1], box[1][1]])).all():
        return flat
    for axis in (0, 1):
        for bound, inside in ((box[axis][0], np.greater_equal), (box[axis][1], np.less_equal)):
            if not len(pts):
                break
            nxt = np.roll(pts, -1, axis=0)
            keep, keep_next = inside(pts[:, axis], bound), inside(nxt[:, axis], bound)
            out = []
            for p, q, p_in, q_in in zip(pts / 4, nxt / 4, keep, keep_next):  # /4: no overflow near 1e308
                if p_in:
                    out.append(p)
                if p_in != q_in:
                    cut = p + (bound / 4 - p[axis]) / (q[axis] - p[axis]) * (q - p)
                    cut[axis] = bound / 4
                    out.append(cut)
            pts = np.array(out).reshape(-1, 2) * 4
    return pts.ravel()


def decode_segmentation(seg: Any, height: int, width: int) -> np.ndarray:
    """Decode a COCO segmentation (polygons, RLE or uncompressed RLE) into an ``(H, W)`` bool mask.

    Raises ``ValueError`` for a malformed segmentation.
    """
    if isinstance(seg, list):
        polys = [p for p in seg if isinstance(p, (list, tuple)) and len(p) >= 6]
        if not polys and any(isinstance(p, dict) for p in seg):
            raise ValueError("segmentation is a list holding an RLE object, not polygons (give the RLE object itself)")
        if not polys:
            raise ValueError("segmentation has no polygon with at least 3 points")
        arr = [np.asarray(p, dtype=np.float64) for p in polys]
        if any(not np.isfinite(a).all() for a in arr):
            raise ValueError("segmentation polygon has NaN or infinite coordinates")
        arr = [a for a in (clip_polygon(a, height, width) for a in arr) if len(a) >= 6]
        if not arr:  # every polygon lies outside the image
            return np.zeros((height, width), dtype=bool)
        rles = mask_utils.frPyObjects([a.tolist() for a in arr], height, width)
        rle = mask_utils.merge(rles)
    elif isinstance(seg, dict) and "counts" in seg:
        if list(seg.get("size", [])) != [height, width]:
            raise ValueError(f"RLE size {seg.get('size')} does not match the image ({height}, {width})")
        if isinstance(seg["counts"], list):
            counts = seg["counts"]
            if not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c <= height * width for c in counts):
                raise ValueError("uncompressed RLE counts must be non-negative integers")
            return decode_counts(np.asarray(counts, dtype=np.int64), height, width)
        text = seg["counts"].encode("ascii") if isinstance(seg["counts"], str) else seg["counts"]
        if not isinstance(text, bytes):
            raise ValueError(f"RLE counts are {_describe(text)}, not a string or a list")
        return decode_counts(rle_counts(text), height, width)
    else:
        raise ValueError("segmentation is neither polygons nor RLE")
    return mask_utils.decode(rle).astype(bool)


def rle_counts(text: bytes) -> np.ndarray:
    """The run lengths of a compressed COCO RLE string (pycocotools' ``counts`` bytes), ``(N,)`` int64.

    Each run is a little-endian sequence of 5-bit groups, one character each (``48 +`` the group, bit 5
    set on every group but the last, bit 4 of the last the sign); from the fourth run on, a run is stored
    as its difference from the run two places before it. ``ValueError`` for a character outside the
    alphabet, a string cut inside a run, a run of over 7 groups (35 bits) or a negative run.

    Example:
        >>> from pycocotools import mask
        >>> m = np.zeros((4, 5), dtype=np.uint8, order="F"); m[1:3, 1:4] = 1
        >>> rle_counts(mask.encode(m)["counts"]).tolist()
        [5, 2, 2, 2, 2, 2, 5]
    """
    c = np.frombuffer(text, dtype=np.uint8) - np.uint8(48)  # a character below "0" wraps above 63
    if not len(c):
        return np.zeros(0, dtype=np.int64)
    if c.max() > 63:
        raise ValueError("RLE counts hold a character outside the compressed alphabet")
    last = c < 32  # the last group of each run
    if not last[-1]:
        raise ValueError("RLE counts end inside a run")
    ends = np.flatnonzero(last)
    starts = np.empty_like(ends)
    starts[0], starts[1:] = 0, ends[:-1] + 1
    groups = ends - starts + 1
    if groups.max() > 7:
        raise ValueError("RLE counts hold a run too long to be a pixel count")
    shift = 5 * (np.arange(len(c)) - np.repeat(starts, groups))
    x = np.add.reduceat((c & 31).astype(np.int64) << shift, starts)
    x -= (c[ends] >= 16) * (np.int64(1) << (5 * groups))  # sign-extend
    x[1::2], x[2::2] = np.cumsum(x[1::2]), np.cumsum(x[2::2])  # undo the differences along each parity
    if (x < 0).any():
        raise ValueError("RLE counts hold a negative run")
    return x


def decode_counts(counts: np.ndarray, height: int, width: int) -> np.ndarray:
    """The ``(H, W)`` bool mask of RLE run lengths (background first, column-major, as COCO stores them),
    checked: ``ValueError`` unless they sum to ``H * W`` (pycocotools leaves the rest of a short mask unset).
    The same array as ``pycocotools.mask.decode(...).astype(bool)``, Fortran order included.

    Example:
        >>> decode_counts(np.array([1, 2, 3]), 2, 3).astype(int).tolist()
        [[0, 1, 0], [1, 0, 0]]
    """
    total = int(counts.sum())
    if total != height * width:
        raise ValueError(f"RLE counts sum to {total}, not width x height = {width} x {height} = {width * height}")
    values = np.zeros(len(counts), dtype=bool)
    values[1::2] = True
    return np.repeat(values, counts).reshape(width, height).T


# --------------------------------------------------------------------------- writing


def make_category(cat_id: int, name: str, keypoints: list[str], *, flip_pairs=None, rigid_keypoints=None,
                  symmetry: str = "none", articulated: bool = False, supercategory: str = "object",
                  left_convention: str | None = None) -> dict:
    """A COCO keypoint category with the carvi extras (flip pairs inferred from names when not given)."""
    return {
        "id": int(cat_id), "name": name, "supercategory": supercategory, "keypoints": list(keypoints),
        "skeleton": [],
        "flip_pairs": [list(p) for p in (flip_pairs if flip_pairs is not None else infer_flip_pairs(keypoints))],
        **({"rigid_keypoints": [int(i) for i in rigid_keypoints]} if rigid_keypoints is not None else {}),
        "symmetry": symmetry, "articulated": bool(articulated),
        **({"left_convention": left_convention} if left_convention is not None else {}),
    }


def make_annotation(ann_id: int, image_id: int, category_id: int, mask: np.ndarray | torch.Tensor,
                    keypoints: np.ndarray, visible: np.ndarray, **extras) -> dict:
    """A COCO keypoint annotation: RLE segmentation, area, bbox, ``[x, y, v] * K`` (v=2 visible, else 0s).

    ``extras`` (``object_id``, ``source``, ``split``, ...) are copied in.
    """
    if isinstance(mask, torch.Tensor):
        mask = mask.detach().cpu().numpy()
    mask = np.asarray(mask, dtype=bool)
    rle = encode_mask(mask)
    ys, xs = np.nonzero(mask)
    bbox = [float(xs.min()), float(ys.min()), float(xs.max() - xs.min() + 1), float(ys.max() - ys.min() + 1)] \
        if len(xs) else [0.0, 0.0, 0.0, 0.0]
    kp = np.asarray(keypoints, dtype=np.float64)
    vis = np.asarray(visible, dtype=bool)
    flat = []
    for (x, y), v in zip(kp, vis):
        flat += [round(float(x), 3), round(float(y), 3), 2] if v else [0, 0, 0]
    return {"id": int(ann_id), "image_id": int(image_id), "category_id": int(category_id), "segmentation": rle,
            "area": float(mask.sum()), "bbox": bbox, "iscrowd": 0, "keypoints": flat,
            "num_keypoints": int(vis.sum()), **extras}


def write_coco(path: str | Path, images: list, annotations: list, categories: list, **extra) -> Path:
    """Write a COCO keypoint dataset atomically."""
    return write_json(path, {"images": images, "annotations": annotations, "categories": categories, **extra},
                      indent=None)


# --------------------------------------------------------------------------- reading


def object_id(value) -> int | str | None:
    """An id as the outputs carry it: an int (not a bool) or a non-empty string; ``None`` when unusable
    (null, a float, a bool, an empty string, a list...).

    Example:
        >>> object_id(7), object_id("aeroplane01"), object_id(7.0), object_id(None), object_id(True)
        (7, 'aeroplane01', None, None, None)
    """
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, str) and value.strip():
        return value
    return None


def _describe(value) -> str:
    kind = {type(None): "null", bool: "a boolean", int: "an integer", float: "a float", str: "a string",
            list: "a list", dict: "an object"}
    return f"{kind.get(type(value), type(value).__name__)} ({json.dumps(value)[:40]})"


def flag(value) -> bool | None:
    """A yes/no annotation field (``occluded``, ``truncated``, ``iscrowd``): JSON booleans, 0 / 1, and
    the strings true/false, yes/no, 1/0 (any case); ``None`` for anything else.

    Example:
        >>> flag(True), flag(0), flag("no"), flag("Yes"), flag("maybe")
        (True, False, False, True, None)
    """
    if isinstance(value, bool):
        return value
    if value is None:
        return False
    if isinstance(value, (int, float)) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in ("true", "yes", "1", "false", "no", "0", ""):
        return value.strip().lower() in ("true", "yes", "1")
    return None


def _category_meta(cat: dict, problems: list) -> ClassMeta | None:
    name = str(cat.get("name", f"category_{cat.get('id')}"))
    names = cat.get("keypoints")
    if not isinstance(names, list) or not names:
        problems.append(Problem("category has no keypoint names", category=name))
        return None
    names = [str(n) for n in names]
    repeated = [n for n, c in Counter(names).items() if c > 1]
    if repeated:  # a name is how a keypoint is found (mean shape, templates, flips): two points cannot share one
        problems.append(Problem(f"keypoint names repeat: {shown_names([shown(n) for n in repeated])}; each "
                                "keypoint needs its own name", category=name))
        return None
    k = len(names)
    pairs = cat.get("flip_pairs")
    if pairs is not None:
        pairs = _flip_pairs(pairs, k)
        if pairs is None:
            problems.append(Problem(f"invalid flip_pairs {shown(cat.get('flip_pairs'), 80)} (pairs of two different "
                                    f"keypoint indices below {k}, each index in one pair at most); inferring them "
                                    "from names", category=name, fatal=False))
    pairs = infer_flip_pairs(names) if pairs is None else pairs
    rigid = cat.get("rigid_keypoints")
    if rigid is not None:
        rigid = _indices(rigid, k)
        if rigid is None or len(set(rigid)) < 3:
            problems.append(Problem(f"invalid rigid_keypoints {shown(cat.get('rigid_keypoints'), 80)} (at least 3 "
                                    f"keypoint indices below {k}); using all keypoints", category=name, fatal=False))
            rigid = None
        else:
            rigid = sorted(set(rigid))
    symmetry = str(cat.get("symmetry", "none"))
    if symmetry not in ("none", "rotational"):
        problems.append(Problem(f"unknown symmetry {symmetry!r}; using 'none'", category=name, fatal=False))
        symmetry = "none"
    convention = str(cat.get("left_convention", "object"))
    if convention not in ("object", "viewer"):
        problems.append(Problem(f"unknown left_convention {convention!r}; using 'object'", category=name, fatal=False))
        convention = "object"
    return ClassMeta(name=name, keypoint_names=names, flip_pairs=[tuple(p) for p in pairs], rigid_keypoints=rigid,
                     symmetry=symmetry, articulated=flag(cat.get("articulated", False)) is True,
                     category_id=object_id(cat.get("id")), left_convention=convention,
                     keypoints_3d=_keypoints_3d(cat, k, name, problems))


def _indices(values, k: int) -> list[int] | None:
    """``values`` as keypoint indices (JSON integers, or integral numbers, in ``[0, k)``), or ``None``."""
    if not (isinstance(values, list) and numbers(values, (len(values),))
            and all(0 <= v < k and float(v).is_integer() for v in values)):
        return None
    return [int(v) for v in values]


def _flip_pairs(pairs, k: int) -> list[tuple[int, int]] | None:
    """A category's ``flip_pairs`` checked: pairs of two different indices, no index in two pairs (so the
    mirror is a permutation); ``None`` when they are not."""
    if not isinstance(pairs, list) or not all(isinstance(p, list) and len(p) == 2 for p in pairs):
        return None
    flat = _indices([i for p in pairs for i in p], k)
    if flat is None or len(set(flat)) != len(flat):
        return None
    return list(zip(flat[0::2], flat[1::2]))


def _keypoints_3d(cat: dict, k: int, name: str, problems: list) -> list | None:
    """The category's ``keypoints_3d`` (``K`` points or nulls), or ``None`` (absent or unusable: reported)."""
    pts = cat.get("keypoints_3d")
    if pts is None:
        return None
    ok = isinstance(pts, list) and len(pts) == k and all(
        p is None or (numbers(p, (3,)) and all(abs(v) < _KEYPOINTS_3D_BOUND for v in p)) for p in pts)
    if not ok:
        problems.append(Problem(f"keypoints_3d must hold {k} points [x, y, z] or nulls; ignored", category=name,
                                fatal=False))
        return None
    return pts


def _parse_keypoints(ann: dict, k: int, width: int, height: int, warn) -> tuple[np.ndarray, np.ndarray] | str:
    """``(K,2)`` coordinates and ``(K,)`` visibility, or a reason string when unusable."""
    kp = ann.get("keypoints")
    if not isinstance(kp, list):
        return "no keypoints list"
    if len(kp) != 3 * k:
        return f"has {len(kp)} keypoint values, the category defines {k} keypoints ({3 * k} values)"
    try:
        arr = np.asarray(kp, dtype=np.float64).reshape(k, 3)
    except (TypeError, ValueError):
        return "keypoints are not numbers"
    except OverflowError:  # a JSON integer beyond float64
        return "a keypoint value is an integer beyond floating point"
    xy, v = arr[:, :2], arr[:, 2]
    visible = v >= 2
    bad = visible & ~np.isfinite(xy).all(axis=1)
    if bad.any():
        warn(f"keypoint(s) {np.nonzero(bad)[0].tolist()} have NaN/infinite coordinates; treated as not visible")
        visible &= ~bad
    far = visible & far_outside(xy, (0, 0), (width - 1, height - 1), max(width, height))
    if far.any():
        warn(f"keypoint(s) {np.nonzero(far)[0].tolist()} lie far outside the {width}x{height} image; "
             "treated as not visible")
        visible &= ~far
    xy = np.where(visible[:, None], xy, 0.0)
    return xy, visible


def load_coco(path: str | Path, *, canvas_size: int = 128, margin: float = 0.1, device: str | torch.device = "cpu",
              classes: Iterable[str] | None = None, skip_flags: bool = True,
              max_image_pixels: int = MAX_IMAGE_PIXELS) -> LoadResult:
    """Read a COCO keypoint file into one :class:`ClassCollection` per category.

    Args:
        path: the JSON file.
        canvas_size, margin: canvas of the collections (see :func:`canvas_similarity`).
        device: device of the returned tensors.
        classes: keep only these categories (by name, or by their folder name ``ClassMeta.key``).
        skip_flags: skip annotations flagged ``occluded`` / ``truncated`` / ``iscrowd``.
        max_image_pixels: skip objects whose image has more pixels (their mask would not fit in memory).

    Returns:
        :class:`LoadResult`, collections keyed by ``ClassMeta.key`` (two categories of one name are two
        classes with different keys). A category without keypoint names or with a repeated one is skipped
        (one :class:`Problem` naming it and the names). Objects are skipped (with a :class:`Problem`) for: an
        unusable or duplicate id (or one whose output files an earlier id names, :func:`_claim_id`), unknown
        category or image, an image too large or without a size, keypoint count not matching the category, no
        visible keypoint, missing/empty/malformed mask, occluded/truncated flags (or unreadable ones). NaN or
        far-outside keypoints are dropped with a warning.

    Raises:
        CocoFormatError: the file is missing, not UTF-8, not JSON (message with line and column), nested
            too deeply, or has no ``annotations`` / ``categories`` lists, or ``images`` that is not a list.
    """
    data = _read(Path(path))
    problems: list[Problem] = []
    metas = _categories(data["categories"], set(classes) if classes else None, problems)
    images = _images(data.get("images") or [], problems)
    by_key = {key: meta for key, meta in metas.values() if meta is not None}
    per_class: dict[str, _Canvases] = {}
    seen: dict[str, dict] = {}
    with watch_interrupts() as interrupts:
        for ann in data["annotations"]:
            item = _annotation(ann, metas, images, seen, skip_flags, max_image_pixels, problems)
            interrupts.check()  # a Ctrl-C that a library turned into a bad-input error stops the load
            if item is not None:
                if item[0] not in per_class:
                    per_class[item[0]] = _Canvases(by_key[item[0]], canvas_size, margin)
                per_class[item[0]].add(item[1:])
    collections = {key: _build_collection(c, torch.device(device)) for key, c in per_class.items()}
    return LoadResult(collections=collections, problems=problems, dataset=data)


def _read(path: Path) -> dict:
    try:
        data = read_json(path)
    except (FileNotFoundError, ValueError) as e:
        raise CocoFormatError(str(e)) from None
    except OSError as e:
        raise CocoFormatError(f"{path}: {os_error_line(e, said=path)}") from None
    if not isinstance(data, dict):
        raise CocoFormatError(f"{path}: expected a JSON object with images, annotations and categories")
    for key in ("annotations", "categories"):
        if not isinstance(data.get(key), list):
            raise CocoFormatError(f"{path}: missing or invalid '{key}' list")
    if data.get("images") is not None and not isinstance(data["images"], list):
        raise CocoFormatError(f"{path}: 'images' is {_describe(data['images'])}, not a list")
    return data


def _categories(cats: list, wanted: set | None, problems: list) -> dict:
    """``{category id as str: (key, ClassMeta or None)}``: every category with a usable id (``None``:
    a broken category or one ``wanted`` leaves out), each with a safe folder name unique in the file."""
    out: dict = {}
    taken: set[str] = set()
    for cat in cats:
        cid = object_id(cat.get("id")) if isinstance(cat, dict) else None
        if cid is None:
            problems.append(Problem(f"category entry without a usable id: {str(cat)[:80]}"))
            continue
        if str(cid) in out:
            problems.append(Problem(f"duplicate category id {cid!r}; keeping the first", fatal=False))
            continue
        meta = _category_meta(cat, problems)
        if meta is not None:
            meta.key = _unique_key(meta.name, cid, taken)
            if meta.key != meta.name:
                problems.append(Problem(f"category {meta.name!r} (id {cid!r}) is written to the folder "
                                        f"{meta.key!r}", category=meta.name, fatal=False))
            if wanted is not None and not ({meta.name, meta.key} & wanted):
                meta = None
        out[str(cid)] = (meta.key if meta else None, meta)
    return out


def class_keys(categories: list) -> dict[str, str]:
    """``{category id as str: class key}`` of a file's categories, as :func:`load_coco` names their
    folders (readers of a run's outputs find a class's folder with it).

    Example:
        >>> class_keys([{"id": 1, "name": "car", "keypoints": ["a"]}, {"id": 2, "name": "car", "keypoints": ["a"]}])
        {'1': 'car', '2': 'car-2'}
    """
    return {cid: key for cid, (key, meta) in _categories(categories, None, []).items() if meta is not None}


def class_names(categories: list) -> dict[str, list[str]]:
    """``{name: class keys}``: every name a file's usable categories answer to (a category's name and its folder
    name, as :func:`load_coco`'s ``classes`` matches them) with the class folders it selects.

    Example:
        >>> class_names([{"id": 1, "name": "car", "keypoints": ["a"]}, {"id": 2, "name": "car", "keypoints": ["a"]}])
        {'car': ['car', 'car-2'], 'car-2': ['car-2']}
    """
    names: dict[str, list[str]] = {}
    for key, meta in _categories(categories, None, []).values():
        if meta is not None:
            for name in dict.fromkeys((key, meta.name)):
                names.setdefault(name, []).append(key)
    return dict(sorted(names.items()))


def select_classes(asked, names: dict, where: str) -> list[str]:
    """The class folders that the names ``asked`` (``--classes``) select among ``names`` (:func:`class_names`);
    ``ValueError`` naming every name that is none of them, ``where``'s classes and that case matters: the one
    check of the commands that take ``--classes``.

    Example:
        >>> select_classes(["Car"], {"car": ["car"]}, "data.json")
        Traceback (most recent call last):
        ...
        ValueError: --classes: 'Car' is not a class of data.json (its classes: car; names are case-sensitive)
    """
    unknown = [c for c in asked if c not in names]
    if unknown:
        keys = sorted({k for ks in names.values() for k in ks})
        raise ValueError(f"--classes: {', '.join(map(repr, unknown))} "
                         f"{'is not a class' if len(unknown) == 1 else 'are not classes'} of {where} "
                         f"(its classes: {', '.join(keys) or 'none'}; names are case-sensitive)")
    return sorted({k for c in asked for k in names[c]})


def _unique_key(name: str, cid, taken: set) -> str:
    """A safe folder name for the class, unique in the run and none of the run's own file names
    (case-insensitively)."""
    key = safe_name(name)
    if key.lower() in taken or reserved(key):
        key = safe_name(f"{name}-{cid}")
        n = 2
        while key.lower() in taken or reserved(key):
            key, n = safe_name(f"{name}-{cid}-{n}"), n + 1
    taken.add(key.lower())
    return key


def _images(entries: list, problems: list) -> dict:
    """``{image id as str: image entry}`` of the entries with a usable id."""
    images = {}
    for im in entries:
        iid = object_id(im.get("id")) if isinstance(im, dict) else None
        if iid is None:
            problems.append(Problem(f"image entry without a usable id: {str(im)[:80]}"))
        elif str(iid) in images:
            problems.append(Problem(f"duplicate image id {iid!r}; keeping the first", fatal=False))
        else:
            images[str(iid)] = im
    return images


def _image_size(im: dict, max_pixels: int) -> tuple[int, int] | str:
    """``(width, height)`` of an image entry, or why it is unusable."""
    try:
        width, height = im["width"], im["height"]
        if isinstance(width, bool) or isinstance(height, bool) or int(width) != width or int(height) != height:
            raise ValueError
        width, height = int(width), int(height)
        if width < 1 or height < 1:
            raise ValueError
    except (KeyError, TypeError, ValueError, OverflowError):
        return f"image {im.get('id')!r} has no valid width/height"
    if width * height > max_pixels:
        return (f"image {im.get('id')!r} is {width}x{height} pixels, more than max_image_pixels={max_pixels} "
                "(its mask would not fit in memory)")
    return width, height


def _annotation(ann, metas: dict, images: dict, seen: dict, skip_flags: bool, max_pixels: int, problems: list):
    """One annotation checked and decoded: ``(class key, ann, image, mask, xy, visible)``, or ``None``
    with its :class:`Problem` recorded."""
    if not isinstance(ann, dict):
        problems.append(Problem(f"annotation entry is not an object: {str(ann)[:80]}"))
        return None
    aid, source = object_id(ann.get("id")), ann.get("source")
    source = source if isinstance(source, str) else None
    if aid is None:
        problems.append(Problem(f"annotation id is {_describe(ann.get('id'))}, not an integer or a string",
                                source=source or str(ann)[:60]))
        return None
    first, claimed = _claim_id(aid, seen)
    cid = object_id(ann.get("category_id"))
    if cid is None or str(cid) not in metas:
        if claimed:
            first["why"] = f"unknown category id {shown(ann.get('category_id'))}"
        problems.append(Problem(f"unknown category id {ann.get('category_id')!r}", annotation_id=aid, source=source))
        return None
    key, meta = metas[str(cid)]
    if meta is None:  # left out by `classes`, or a broken category (reported)
        if claimed:
            first["why"] = "its class is left out by the run's classes, or unusable"
        return None
    p = dict(annotation_id=aid, category=meta.name, source=source, class_key=key)
    if not claimed:
        problems.append(Problem(_clash(aid, first), **p))
        return None
    why = _flags(ann) if skip_flags else None
    if why is None:
        why, im, size = _image_of(ann, images, max_pixels)
    if why is None:
        warnings: list[str] = []
        parsed = _parse_keypoints(ann, meta.num_keypoints, size[0], size[1], warnings.append)
        problems.extend(Problem(w, fatal=False, **p) for w in warnings)
        why = parsed if isinstance(parsed, str) else ("no visible keypoint" if not parsed[1].any() else None)
    if why is None:
        mask = _mask(ann, size)
        why = mask if isinstance(mask, str) else None
    if why is not None:
        first["why"] = why
        problems.append(Problem(why, **p))
        return None
    return key, ann, im, mask, parsed[0], parsed[1]


def _claim_id(aid, seen: dict) -> tuple[dict, bool]:
    """The record ``{"id", "why"}`` of the first annotation of the file whose output files ``aid``'s would be
    (the same id, or another that :func:`~carvi_torch.io.layout.object_stem` spells alike: ``"a/b"`` and
    ``"a_b-c14cddc0"``), and whether that is this annotation (then registered); ``why``: the reason the first
    is not reconstructed. Ids that differ in letter case only stay apart, as on a case-sensitive file system."""
    stem = object_stem(aid)
    if stem in seen:
        return seen[stem], False
    seen[stem] = {"id": aid, "why": None}
    return seen[stem], True


def _clash(aid, first: dict) -> str:
    """The reason an annotation whose output files an earlier one claimed (:func:`_claim_id`) is skipped."""
    fate = ("keeping the first" if first["why"] is None
            else f"the first is not reconstructed either: {first['why']}")
    if str(first["id"]) == str(aid):
        return f"{DUPLICATE_ID} {aid!r}; {fate}"
    return (f"annotation id {aid!r} and the earlier {first['id']!r} name the same output files "
            f"({object_stem(first['id'])!r}); {fate}")


def _flags(ann: dict) -> str | None:
    """Why a flagged annotation is not reconstructed (``None``: it is)."""
    set_flags = []
    for name in ("occluded", "truncated", "iscrowd"):
        value = flag(ann.get(name))
        if value is None:
            return f"{name} is {_describe(ann.get(name))}, not a yes/no value"
        if value:
            set_flags.append(name)
    return f"{' and '.join(set_flags)}: not reconstructed" if set_flags else None


def _image_of(ann: dict, images: dict, max_pixels: int):
    """``(reason or None, image entry, (width, height))`` of an annotation's image."""
    iid = object_id(ann.get("image_id"))
    im = images.get(str(iid)) if iid is not None else None
    if im is None:
        return f"unknown image id {ann.get('image_id')!r}", None, None
    size = _image_size(im, max_pixels)
    return (size, None, None) if isinstance(size, str) else (None, im, size)


def _mask(ann: dict, size: tuple[int, int]) -> np.ndarray | str:
    """The decoded, non-empty mask of an annotation, or why there is none."""
    seg = ann.get("segmentation")
    if seg is None or seg == [] or seg == {}:
        return "missing mask (no segmentation)"
    try:
        mask = decode_segmentation(seg, size[1], size[0])
    except (ValueError, TypeError, KeyError, IndexError, OverflowError) as e:  # what garbage raises
        return f"malformed segmentation: {e}"
    return mask if mask.any() else "empty mask"


def _dense(values: list) -> torch.Tensor:
    """``(N,)`` long: equal values get equal indices (object ids may be ints or strings)."""
    index: dict = {}
    return torch.tensor([index.setdefault(v, len(index)) for v in values], dtype=torch.long)


def input_fingerprints(meta: ClassMeta, items: list) -> list[str]:
    """One hash per object of everything of its own that its reconstruction is made from: the class's
    definition (name, category id, keypoint names, flip pairs, rigid keypoints, symmetry, articulation,
    left convention, 3-D template), its annotation, image and object ids, its ``source``, its image's
    ``file_name``, width and height, its decoded mask (shape and bits), and its keypoints and visibility as
    loaded. The annotation file's own path is not part of it (a copy of the file gives the same hashes).

    ``items``: ``(ann, image entry, mask (H, W) bool, xy (K, 2), visible (K,) bool)`` per object, as
    :func:`load_coco` decodes them (a few tens of microseconds each: the mask is hashed as packed bits).

    Example:
        >>> meta = ClassMeta("car", ["a", "b"])
        >>> item = ({"id": 1, "image_id": 7}, {"file_name": "x.jpg", "width": 4, "height": 3},
        ...         np.eye(3, 4, dtype=bool), np.zeros((2, 2)), np.array([True, False]))
        >>> moved = (item[0], item[1], np.eye(3, 4, 1, dtype=bool), item[3], item[4])
        >>> a, b, c = input_fingerprints(meta, [item, item, moved])
        >>> a == b, a == c, len(a)
        (True, False, 32)
    """
    cls = json.dumps([meta.name, meta.category_id, meta.keypoint_names, meta.flip_pairs, meta.rigid_keypoints,
                      meta.symmetry, meta.articulated, meta.left_convention, meta.keypoints_3d], default=str)
    head = hashlib.blake2b(cls.encode(), digest_size=16).digest()
    out = []
    for ann, im, mask, xy, vis in items:
        h = hashlib.blake2b(head, digest_size=16)
        ids = [ann.get("id"), ann.get("image_id"), ann.get("object_id"), ann.get("source"), im.get("file_name"),
               im.get("width"), im.get("height")]
        h.update(json.dumps(ids, default=str).encode())
        mask = np.asarray(mask, dtype=bool)
        h.update(np.asarray(mask.shape, dtype=np.int64).tobytes() + np.packbits(mask).tobytes())
        h.update(np.ascontiguousarray(xy, dtype=np.float64).tobytes() + np.asarray(vis, dtype=np.uint8).tobytes())
        out.append(h.hexdigest())
    return out


class _Canvases:
    """One class's objects as the load decodes them: every :attr:`CHUNK` objects their image-size masks are
    resampled into canvases (box = mask extent, :func:`canvas_similarity`) and hashed (:func:`input_fingerprints`),
    then dropped, so a load holds at most ``CHUNK`` image-size masks per class (about 0.3 MB each at 640 x 480)
    whatever its size. Each object's canvas and similarity are its own (no operation mixes objects), so the chunks
    change no bit: the chunks' similarities joined (:meth:`similarity`) are those of all boxes at once."""

    CHUNK = 256

    def __init__(self, meta: ClassMeta, canvas_size: int, margin: float):
        self.meta, self.canvas_size, self.margin = meta, canvas_size, margin
        self.items: list = []  # (ann, image entry, xy, visible) per object, masks dropped
        self.similarities: list[Similarity2D] = []  # per chunk: scale (n,), offset (n, 2)
        self.canvases: list[torch.Tensor] = []
        self.fingerprints: list[str] = []
        self.pending: list = []  # (ann, image entry, mask, xy, visible) not resampled yet

    def add(self, item: tuple) -> None:
        self.pending.append(item)
        if len(self.pending) >= self.CHUNK:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        boxes = []
        for _ann, _im, mask, _xy, _vis in self.pending:
            ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))  # occupied rows, columns
            boxes.append([xs[0], ys[0], xs[-1], ys[-1]])
        sim = canvas_similarity(torch.tensor(boxes, dtype=torch.float32), self.canvas_size, self.margin)
        # a few small operations per object: intra-op threads only add their synchronisation (on a busy
        # 2-core machine 584 objects took 33 s with 2 threads, 2.2 s with 1). Same values either way.
        with torch_threads(1):
            self.canvases.append(resample_to_canvases([torch.from_numpy(it[2]) for it in self.pending], sim.scale,
                                                      sim.offset, self.canvas_size))
        self.fingerprints += input_fingerprints(self.meta, self.pending)
        self.similarities.append(sim)
        self.items += [(ann, im, xy, vis) for ann, im, _mask, xy, vis in self.pending]
        self.pending = []

    def similarity(self) -> Similarity2D:
        """The image -> canvas similarity of every object flushed so far, in the order they were added."""
        return Similarity2D(torch.cat([s.scale for s in self.similarities]),
                            torch.cat([s.offset for s in self.similarities]))


def _build_collection(canvases: _Canvases, device: torch.device) -> ClassCollection:
    """The class's collection from its objects' canvases (:class:`_Canvases`); visible keypoints may stick out
    of the canvas a little."""
    canvases.flush()
    meta, items = canvases.meta, canvases.items
    sim = canvases.similarity()
    masks = torch.cat(canvases.canvases)
    xy = torch.tensor(np.stack([it[2] for it in items]), dtype=torch.float32)
    vis = torch.tensor(np.stack([it[3] for it in items]), dtype=torch.bool)
    kp = torch.where(vis[..., None], sim.apply(xy), torch.zeros_like(xy))
    anns = [it[0] for it in items]
    ims = [it[1] for it in items]
    aids = [object_id(a["id"]) for a in anns]
    # an annotation without a usable object_id is its own object
    oids = [("object", str(object_id(a.get("object_id")))) if object_id(a.get("object_id")) is not None
            else ("annotation", str(aid)) for a, aid in zip(anns, aids)]
    coll = ClassCollection(
        meta=meta,
        masks=masks,
        keypoints=kp,
        visible=vis,
        canvas_from_image=sim,
        image_size=torch.tensor([[int(im["width"]), int(im["height"])] for im in ims], dtype=torch.long),
        annotation_ids=aids,
        image_ids=[object_id(a["image_id"]) for a in anns],
        object_ids=[object_id(a.get("object_id")) for a in anns],
        object_groups=_dense(oids),
        is_mirror=torch.zeros(len(items), dtype=torch.bool),
        sources=[str(a.get("source") or f"annotation {a['id']}") for a in anns],
        splits=[str(a.get("split", "")) for a in anns],
        fingerprints=canvases.fingerprints,
    )
    return coll.to(device)
