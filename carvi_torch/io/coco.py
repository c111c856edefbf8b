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

from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch
from pycocotools import mask as mask_utils

from ..collection import ClassCollection, ClassMeta, canvas_similarity, infer_flip_pairs, resample_to_canvas
from .outputs import read_json, write_json

__all__ = ["CocoFormatError", "Problem", "LoadResult", "load_coco", "encode_mask", "decode_segmentation",
           "make_category", "make_annotation", "write_coco", "OUTSIDE_TOLERANCE"]

#: Keypoints farther outside the image than this fraction of its larger side are rejected.
OUTSIDE_TOLERANCE = 0.5


class CocoFormatError(ValueError):
    """The annotation file cannot be read at all (names the file and the problem)."""


@dataclass
class Problem:
    """One object (or class) that could not be used, and why."""

    reason: str
    annotation_id: int | None = None
    category: str | None = None
    source: str | None = None
    stage: str = "load"
    fatal: bool = True  # False: a warning, the object is still used

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
    rle = mask_utils.encode(np.asfortranarray(np.asarray(mask, dtype=np.uint8)))
    rle["counts"] = rle["counts"].decode("ascii")
    return {"size": [int(v) for v in rle["size"]], "counts": rle["counts"]}


def decode_segmentation(seg: Any, height: int, width: int) -> np.ndarray:
    """Decode a COCO segmentation (polygons, RLE or uncompressed RLE) into an ``(H, W)`` bool mask.

    Raises ``ValueError`` for a malformed segmentation.
    """
    if isinstance(seg, list):
        polys = [p for p in seg if isinstance(p, (list, tuple)) and len(p) >= 6]
        if not polys:
            raise ValueError("segmentation has no polygon with at least 3 points")
        arr = [np.asarray(p, dtype=np.float64) for p in polys]
        if any(not np.isfinite(a).all() for a in arr):
            raise ValueError("segmentation polygon has NaN or infinite coordinates")
        rles = mask_utils.frPyObjects([a.tolist() for a in arr], height, width)
        rle = mask_utils.merge(rles)
    elif isinstance(seg, dict) and "counts" in seg:
        if list(seg.get("size", [])) != [height, width]:
            raise ValueError(f"RLE size {seg.get('size')} does not match the image ({height}, {width})")
        if isinstance(seg["counts"], list):
            rle = mask_utils.frPyObjects(seg, height, width)
        else:
            rle = {"size": seg["size"], "counts": seg["counts"].encode("ascii") if isinstance(seg["counts"], str)
                   else seg["counts"]}
    else:
        raise ValueError("segmentation is neither polygons nor RLE")
    return mask_utils.decode(rle).astype(bool)


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


def _category_meta(cat: dict, problems: list) -> ClassMeta | None:
    name = str(cat.get("name", f"category_{cat.get('id')}"))
    names = cat.get("keypoints")
    if not isinstance(names, list) or not names:
        problems.append(Problem("category has no keypoint names", category=name))
        return None
    names = [str(n) for n in names]
    k = len(names)
    pairs = cat.get("flip_pairs")
    if pairs is None:
        pairs = infer_flip_pairs(names)
    else:
        try:
            pairs = [(int(a), int(b)) for a, b in pairs]
            if any(not (0 <= a < k and 0 <= b < k) for a, b in pairs):
                raise ValueError
        except (TypeError, ValueError):
            problems.append(Problem(f"invalid flip_pairs {cat.get('flip_pairs')!r}; inferring them from names",
                                    category=name, fatal=False))
            pairs = infer_flip_pairs(names)
    rigid = cat.get("rigid_keypoints")
    if rigid is not None:
        try:
            rigid = sorted({int(i) for i in rigid})
            if any(not 0 <= i < k for i in rigid) or len(rigid) < 3:
                raise ValueError
        except (TypeError, ValueError):
            problems.append(Problem(f"invalid rigid_keypoints {cat.get('rigid_keypoints')!r}; using all keypoints",
                                    category=name, fatal=False))
            rigid = None
    symmetry = str(cat.get("symmetry", "none"))
    if symmetry not in ("none", "rotational"):
        problems.append(Problem(f"unknown symmetry {symmetry!r}; using 'none'", category=name, fatal=False))
        symmetry = "none"
    convention = str(cat.get("left_convention", "object"))
    if convention not in ("object", "viewer"):
        problems.append(Problem(f"unknown left_convention {convention!r}; using 'object'", category=name, fatal=False))
        convention = "object"
    return ClassMeta(name=name, keypoint_names=names, flip_pairs=[tuple(p) for p in pairs], rigid_keypoints=rigid,
                     symmetry=symmetry, articulated=bool(cat.get("articulated", False)),
                     category_id=int(cat["id"]), left_convention=convention)


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
    xy, v = arr[:, :2], arr[:, 2]
    visible = v >= 2
    bad = visible & ~np.isfinite(xy).all(axis=1)
    if bad.any():
        warn(f"keypoint(s) {np.nonzero(bad)[0].tolist()} have NaN/infinite coordinates; treated as not visible")
        visible &= ~bad
    tol = OUTSIDE_TOLERANCE * max(width, height)
    with np.errstate(invalid="ignore"):
        far = visible & ((xy[:, 0] < -tol) | (xy[:, 1] < -tol) | (xy[:, 0] > width - 1 + tol)
                         | (xy[:, 1] > height - 1 + tol))
    if far.any():
        warn(f"keypoint(s) {np.nonzero(far)[0].tolist()} lie far outside the {width}x{height} image; "
             "treated as not visible")
        visible &= ~far
    xy = np.where(visible[:, None], xy, 0.0)
    return xy, visible


def load_coco(path: str | Path, *, canvas_size: int = 128, margin: float = 0.1, device: str | torch.device = "cpu",
              classes: Iterable[str] | None = None, skip_flags: bool = True) -> LoadResult:
    """Read a COCO keypoint file into one :class:`ClassCollection` per category.

    Args:
        path: the JSON file.
        canvas_size, margin: canvas of the collections (see :func:`canvas_similarity`).
        device: device of the returned tensors.
        classes: keep only these category names.
        skip_flags: skip annotations flagged ``occluded`` / ``truncated`` / ``iscrowd``.

    Returns:
        :class:`LoadResult`. Objects are skipped (with a :class:`Problem`) for: unknown category or image,
        duplicate id, keypoint count not matching the category, no visible keypoint, missing/empty/
        malformed mask, occluded/truncated flags. NaN or far-outside keypoints are dropped with a warning.

    Raises:
        CocoFormatError: the file is missing, not JSON (message with line and column) or has no
            ``annotations`` / ``categories`` lists.
    """
    path = Path(path)
    try:
        data = read_json(path)
    except (FileNotFoundError, ValueError) as e:
        raise CocoFormatError(str(e)) from None
    if not isinstance(data, dict):
        raise CocoFormatError(f"{path}: expected a JSON object with images, annotations and categories")
    for key in ("annotations", "categories"):
        if not isinstance(data.get(key), list):
            raise CocoFormatError(f"{path}: missing or invalid '{key}' list")
    problems: list[Problem] = []
    wanted = set(classes) if classes else None

    metas: dict[int, ClassMeta] = {}
    for cat in data["categories"]:
        if not isinstance(cat, dict) or "id" not in cat:
            problems.append(Problem(f"category entry without an id: {str(cat)[:80]}"))
            continue
        if int(cat["id"]) in metas:
            problems.append(Problem(f"duplicate category id {cat['id']}; keeping the first", fatal=False))
            continue
        meta = _category_meta(cat, problems)
        if meta is not None and (wanted is None or meta.name in wanted):
            metas[meta.category_id] = meta
    images = {}
    for im in data.get("images", []) or []:
        try:
            images[int(im["id"])] = im
        except (KeyError, TypeError, ValueError):
            problems.append(Problem(f"image entry without a valid id: {str(im)[:80]}"))

    per_class: dict[int, list] = defaultdict(list)
    seen: set[int] = set()
    known_cats = {int(c["id"]) for c in data["categories"] if isinstance(c, dict) and "id" in c}
    for ann in data["annotations"]:
        if not isinstance(ann, dict) or "id" not in ann:
            problems.append(Problem(f"annotation entry without an id: {str(ann)[:80]}"))
            continue
        aid = int(ann["id"])
        source = ann.get("source")
        cid = ann.get("category_id")
        if cid is None or int(cid) not in known_cats:
            problems.append(Problem(f"unknown category id {cid}", annotation_id=aid, source=source))
            continue
        if int(cid) not in metas:  # filtered out by `classes` or a broken category
            continue
        meta = metas[int(cid)]
        p = dict(annotation_id=aid, category=meta.name, source=source)
        if aid in seen:
            problems.append(Problem(f"duplicate annotation id {aid}; keeping the first", **p))
            continue
        seen.add(aid)
        if skip_flags:
            flags = [f for f in ("occluded", "truncated", "iscrowd") if ann.get(f)]
            if flags:
                problems.append(Problem(f"{' and '.join(flags)}: not reconstructed", **p))
                continue
        im = images.get(int(ann.get("image_id", -1)))
        if im is None:
            problems.append(Problem(f"unknown image id {ann.get('image_id')}", **p))
            continue
        try:
            width, height = int(im["width"]), int(im["height"])
            if width < 1 or height < 1:
                raise ValueError
        except (KeyError, TypeError, ValueError):
            problems.append(Problem(f"image {im.get('id')} has no valid width/height", **p))
            continue
        warnings: list[str] = []
        parsed = _parse_keypoints(ann, meta.num_keypoints, width, height, warnings.append)
        for w in warnings:
            problems.append(Problem(w, fatal=False, **p))
        if isinstance(parsed, str):
            problems.append(Problem(parsed, **p))
            continue
        xy, vis = parsed
        if not vis.any():
            problems.append(Problem("no visible keypoint", **p))
            continue
        seg = ann.get("segmentation")
        if seg is None or seg == [] or seg == {}:
            problems.append(Problem("missing mask (no segmentation)", **p))
            continue
        try:
            mask = decode_segmentation(seg, height, width)
        except Exception as e:  # pycocotools raises various types on garbage
            problems.append(Problem(f"malformed segmentation: {e}", **p))
            continue
        if not mask.any():
            problems.append(Problem("empty mask", **p))
            continue
        per_class[meta.category_id].append((ann, im, mask, xy, vis))

    collections = {}
    for cid, items in per_class.items():
        meta = metas[cid]
        collections[meta.name] = _build_collection(meta, items, canvas_size, margin, torch.device(device))
    return LoadResult(collections=collections, problems=problems, dataset=data)


def _build_collection(meta: ClassMeta, items: list, canvas_size: int, margin: float,
                      device: torch.device) -> ClassCollection:
    """Crop each object into the canvas (box = mask extent; visible keypoints may stick out a little)."""
    boxes = []
    for _ann, _im, mask, _xy, _vis in items:
        ys, xs = np.nonzero(mask)
        boxes.append([xs.min(), ys.min(), xs.max(), ys.max()])
    sim = canvas_similarity(torch.tensor(boxes, dtype=torch.float32), canvas_size, margin)
    masks = torch.stack([
        resample_to_canvas(torch.from_numpy(m), float(sim.scale[i]), sim.offset[i], canvas_size)
        for i, (_a, _im, m, _xy, _v) in enumerate(items)
    ])
    xy = torch.tensor(np.stack([it[3] for it in items]), dtype=torch.float32)
    vis = torch.tensor(np.stack([it[4] for it in items]), dtype=torch.bool)
    kp = torch.where(vis[..., None], sim.apply(xy), torch.zeros_like(xy))
    anns = [it[0] for it in items]
    ims = [it[1] for it in items]
    aids = torch.tensor([int(a["id"]) for a in anns], dtype=torch.long)
    oids = torch.tensor([int(a["object_id"]) if a.get("object_id") is not None else -1 - int(a["id"])
                         for a in anns], dtype=torch.long)
    coll = ClassCollection(
        meta=meta,
        masks=masks,
        keypoints=kp,
        visible=vis,
        canvas_from_image=sim,
        image_size=torch.tensor([[int(im["width"]), int(im["height"])] for im in ims], dtype=torch.long),
        annotation_ids=aids,
        image_ids=torch.tensor([int(a["image_id"]) for a in anns], dtype=torch.long),
        object_ids=oids,
        is_mirror=torch.zeros(len(items), dtype=torch.bool),
        sources=[str(a.get("source") or f"annotation {a['id']}") for a in anns],
        splits=[str(a.get("split", "")) for a in anns],
    )
    return coll.to(device)
