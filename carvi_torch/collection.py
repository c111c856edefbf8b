"""Class collections: all instances of one object class as canvas tensors.

Images differ in size, so each instance's mask and keypoints are cropped around
the object and scaled into one square canvas of ``canvas_size`` pixels: a uniform
scale ``a`` and offset ``b`` per instance, ``canvas = a * image + b`` (recorded in
``canvas_from_image``). Every stage works in canvas pixels; a camera estimated in
canvas pixels maps back to image pixels exactly with
``cam.compose_similarity(canvas_from_image.inverse())``.

Mirroring adds the left-right flipped copy of an instance: canvas ``x' = C - 1 - x``,
keypoints swapped along the class's flip pairs (a left keypoint of the flipped
image is the right keypoint of the original). The mirrored copy is the flipped
*image*: its image x is ``w - 1 - x`` (``w`` the image width), so its canvas
similarity has the same scale and offset ``b_x' = C - 1 - a (w - 1) - b_x``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field, fields, replace
from typing import Sequence

import torch
import torch.nn.functional as F

from .cameras import Similarity2D

__all__ = ["ClassMeta", "ClassCollection", "infer_flip_pairs", "mirror_name", "keypoint_side", "name_words",
           "flip_permutation", "canvas_similarity", "resample_to_canvas", "resample_to_canvases", "canvas_supersample"]


# --------------------------------------------------------------------------- left/right names

_SIDE_SWAP = {"left": "right", "right": "left", "l": "r", "r": "l"}
#: The words of a keypoint name: runs of letters split at case changes (``LWing``: ``L``, ``Wing``; ``leftEye``:
#: ``left``, ``Eye``; ``LEFT_EAR``: ``LEFT``, ``EAR``) and runs of digits; every other character separates them.
NAME_WORD = re.compile(r"[A-Z]?[a-z]+|[A-Z]+(?![a-z])|\d+")


def _match_case(word: str, like: str) -> str:
    """``word`` written in the case pattern of ``like`` (``L`` -> ``R``, ``Left`` -> ``Right``)."""
    if like.isupper():
        return word.upper()
    if like[:1].isupper():
        return word[:1].upper() + word[1:]
    return word


def _side_head(token: str) -> str:
    """The part of a name's word that names a side: the whole word when it is ``left``/``right``/``l``/``r`` (any
    case), its start when it starts with ``left`` or ``right`` (``leftcorner``: ``left``), else ``""``.
    Single letters count only as whole words. A word that merely starts with a side word counts too
    (``Leftover``: ``Left``): keypoint names are not prose."""
    low = token.lower()
    if low in _SIDE_SWAP:
        return token
    return next((token[:len(side)] for side in ("left", "right") if low.startswith(side)), "")


def _swap_token(token: str) -> str:
    """A name part with its side (:func:`_side_head`) swapped, or unchanged when it names no side
    (``leftcorner`` -> ``rightcorner``, ``L`` -> ``R``)."""
    head = _side_head(token)
    return _match_case(_SIDE_SWAP[head.lower()], head) + token[len(head):] if head else token


def name_words(name: str) -> list[str]:
    """Lower-cased words of a keypoint name (:data:`NAME_WORD`).

    Example:
        >>> name_words("L_EarBase"), name_words("Upper_Neck_Base"), name_words("wheel1L")
        (['l', 'ear', 'base'], ['upper', 'neck', 'base'], ['wheel', '1', 'l'])
    """
    return [w.lower() for w in NAME_WORD.findall(name)]


def keypoint_side(name: str) -> str | None:
    """``"left"``, ``"right"`` or ``None`` from a keypoint name: the side its parts name (:func:`mirror_name`'s
    rule), ``None`` when they name both or neither.

    Example:
        >>> keypoint_side("L_Stabilizer"), keypoint_side("leftcorner_windshield"), keypoint_side("tail")
        ('left', 'left', None)
    """
    sides = {"left" if h in ("left", "l") else "right" for h in map(_side_head, name_words(name)) if h}
    return sides.pop() if len(sides) == 1 else None


def mirror_name(name: str) -> str:
    """The keypoint name with every side word (:data:`NAME_WORD`) swapped, case and every other character kept
    (``L_WingTip`` -> ``R_WingTip``).

    Example:
        >>> mirror_name("body_back_left_lower"), mirror_name("leftEye"), mirror_name("LWing"), mirror_name("NoseTip")
        ('body_back_right_lower', 'rightEye', 'RWing', 'NoseTip')
    """
    return NAME_WORD.sub(lambda m: _swap_token(m.group(0)), name)


def infer_flip_pairs(names: Sequence[str]) -> list[tuple[int, int]]:
    """Left/right keypoint pairs from their names.

    Every word of a name (:data:`NAME_WORD`: letters split at case changes, digits, the rest separators) that
    names a side is swapped at once: ``left``/``right`` and ``l``/``r`` as whole words in any case and position
    (``left_wing``, ``body_back_left_lower``, ``L_WingTip``, ``LWing``, ``Left_Wing_Base``, ``wheel_l``, ``leftEye``)
    and ``left``/``right`` as the start of a longer word (``leftcorner_windshield``). ``i`` and ``j`` pair when
    the swapped name of ``names[i]`` is exactly ``names[j]``.

    Args:
        names: keypoint names of one class (``K`` strings).

    Returns:
        Sorted list of ``(i, j)`` with ``i < j``; each index appears at most once.

    Example:
        >>> infer_flip_pairs(["L_WingTip", "NoseTip", "R_WingTip"])
        [(0, 2)]
    """
    names = [str(n) for n in names]
    index: dict[str, int] = {}
    for i, n in enumerate(names):
        index.setdefault(n, i)
    pairs: list[tuple[int, int]] = []
    used: set[int] = set()
    for i, n in enumerate(names):
        if i in used:
            continue
        j = index.get(mirror_name(n))
        if j is None or j == i or j in used:
            continue
        pairs.append((min(i, j), max(i, j)))
        used.update((i, j))
    return sorted(pairs)


def flip_permutation(num_keypoints: int, flip_pairs: Sequence[Sequence[int]], device=None) -> torch.Tensor:
    """``(K,)`` long permutation swapping each flip pair (an involution).

    Example:
        >>> flip_permutation(4, [(0, 2)])
        tensor([2, 1, 0, 3])
    """
    perm = torch.arange(num_keypoints, device=device)
    for i, j in flip_pairs:
        perm[i], perm[j] = int(j), int(i)
    return perm


# --------------------------------------------------------------------------- canvas


def canvas_similarity(boxes: torch.Tensor, canvas_size: int, margin: float) -> Similarity2D:
    """Per-instance image -> canvas similarity centring each box in the canvas.

    Args:
        boxes: ``(N, 4)`` float ``(x0, y0, x1, y1)`` in image pixel coordinates (pixel centres,
            inclusive), e.g. the extreme foreground pixel centres.
        canvas_size: canvas side ``C``.
        margin: fraction of the canvas left free on each side.

    Returns:
        ``Similarity2D`` with ``scale (N,)`` and ``offset (N, 2)``: the box's longer side (plus one
        pixel) spans ``C (1 - 2 margin)`` canvas pixels and its centre maps to ``((C-1)/2, (C-1)/2)``.
    """
    side = torch.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1]) + 1.0
    scale = canvas_size * (1.0 - 2.0 * margin) / side.clamp(min=1.0)
    centre = torch.stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2], dim=-1)
    offset = (canvas_size - 1) / 2.0 - scale[:, None] * centre
    return Similarity2D(scale, offset)


def resample_to_canvas(mask: torch.Tensor, scale: float, offset, canvas_size: int,
                       supersample: int | None = None) -> torch.Tensor:
    """Resample one image-size mask into the canvas.

    Each canvas pixel is the average of ``supersample x supersample`` bilinear samples of the image mask
    at sub-pixel positions (``x_img = (x_canvas - b_x) / a``), thresholded at 0.5 — an area average
    when the canvas is coarser than the image.

    Args:
        mask: ``(h, w)`` bool image mask.
        scale: ``a``; offset: ``b``, a ``(2,)`` tensor or two floats.
        canvas_size: ``C``.
        supersample: sub-samples per axis; default ``round(1 / a)`` clamped to [1, 4] (:func:`canvas_supersample`).

    Returns:
        ``(C, C)`` bool.
    """
    h, w = mask.shape
    dev = mask.device
    k = canvas_supersample(scale) if supersample is None else supersample
    sub = (torch.arange(k, device=dev, dtype=torch.float32) + 0.5) / k - 0.5  # sub-pixel offsets
    c = torch.arange(canvas_size, device=dev, dtype=torch.float32)
    xs = (c[:, None] + sub[None, :]).reshape(-1)  # (C*k,)
    ximg = (xs - float(offset[0])) / scale
    yimg = (xs - float(offset[1])) / scale
    gx = 2.0 * ximg / max(w - 1, 1) - 1.0
    gy = 2.0 * yimg / max(h - 1, 1) - 1.0
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], dim=-1)[None]  # (1, Ck, Ck, 2) (x, y)
    samples = F.grid_sample(mask[None, None].float(), grid, mode="bilinear", padding_mode="zeros",
                            align_corners=True)[0, 0]
    avg = samples.reshape(canvas_size, k, canvas_size, k).mean(dim=(1, 3))
    return avg >= 0.5


def canvas_supersample(scale: float) -> int:
    """Sub-samples per axis of a canvas pixel at image-to-canvas scale ``a``: ``round(1 / a)`` in [1, 4].

    Example:
        >>> canvas_supersample(0.83), canvas_supersample(0.4), canvas_supersample(0.01)
        (1, 2, 4)
    """
    return int(min(4, max(1, round(1.0 / max(scale, 1e-6)))))


def resample_to_canvases(masks: Sequence[torch.Tensor], scale: torch.Tensor, offset: torch.Tensor,
                         canvas_size: int) -> torch.Tensor:
    """:func:`resample_to_canvas` of many masks, in under half its time: bit for bit on the CPU (what loading
    passes); on a GPU to float rounding (CUDA divides by a Python number through its reciprocal).

    The sample positions of all objects are computed at once, each object's sub-samples are laid out
    sub-sample-major (``(k, C, k, C)``: contiguous blocks) and summed in the order the reference's mean
    sums them, so every canvas is the reference's exactly (``tests/test_collection.py``).

    Args:
        masks: ``N`` image masks ``(h_i, w_i)`` bool, on the CPU or one device.
        scale: ``(N,)``; offset: ``(N, 2)``: the image-to-canvas similarities (:func:`canvas_similarity`).
        canvas_size: ``C``.

    Returns:
        ``(N, C, C)`` bool on the masks' device.

    Example:
        >>> m = torch.zeros(6, 8, dtype=torch.bool); m[1:5, 2:6] = True
        >>> out = resample_to_canvases([m], torch.tensor([2.0]), torch.tensor([[-1.0, 0.0]]), 16)
        >>> torch.equal(out[0], resample_to_canvas(m, 2.0, [-1.0, 0.0], 16))
        True
    """
    N = len(masks)
    if scale.shape != (N,) or offset.shape != (N, 2):
        raise ValueError(f"{N} masks need scale (N,) and offset (N, 2), got {tuple(scale.shape)} and "
                         f"{tuple(offset.shape)}")
    dev = masks[0].device if N else torch.device("cpu")
    if N == 0:
        return torch.zeros(0, canvas_size, canvas_size, dtype=torch.bool)
    ks = [canvas_supersample(a) for a in scale.tolist()]
    axes = _sample_axes(masks, scale.to(dev, torch.float32), offset.to(dev, torch.float32), canvas_size, ks)

    return torch.stack([_resample_one(masks[i], *axes[i], ks[i], canvas_size) for i in range(N)])


def _sample_axes(masks, scale: torch.Tensor, offset: torch.Tensor, C: int, ks: list[int]) -> list:
    """Per object its grid_sample x and y coordinates ``((k C,), (k C,))``, sub-sample-major, computed for
    all objects of one ``k`` at once with the reference's float32 operations in its order."""
    dev = scale.device
    size = torch.tensor([list(m.shape) for m in masks], dtype=torch.float32, device=dev)  # (N, 2) h, w
    span = (size - 1).clamp(min=1)
    out: list = [None] * len(masks)
    for k in sorted(set(ks)):
        idx = [i for i, kk in enumerate(ks) if kk == k]
        sub = (torch.arange(k, device=dev, dtype=torch.float32) + 0.5) / k - 0.5
        xs = (torch.arange(C, device=dev, dtype=torch.float32)[None, :] + sub[:, None]).reshape(-1)
        rows = torch.tensor(idx, device=dev)
        a, b = scale[rows, None], offset[rows]
        gx = 2.0 * ((xs - b[:, 0:1]) / a) / span[rows, 1:2] - 1.0
        gy = 2.0 * ((xs - b[:, 1:2]) / a) / span[rows, 0:1] - 1.0
        for j, i in enumerate(idx):
            out[i] = (gx[j], gy[j])
    return out


def _resample_one(mask: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor, k: int, C: int) -> torch.Tensor:
    """One canvas from its sub-sample-major axes (:func:`_sample_axes`)."""
    n = len(gx)
    grid = torch.stack((gx.expand(n, n), gy[:, None].expand(n, n)), dim=-1)[None]  # (1, kC, kC, 2) (x, y)
    # a bool mask read as bytes, clamped to 1 (a bool tensor made from foreign bytes may hold 2 or 255): the
    # same 0 and 1 as bool -> float, in a fraction of the time
    image = (mask.view(torch.uint8).clamp(max=1) if mask.dtype == torch.bool else mask)[None, None].float()
    s = F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=True)[0, 0]
    if k == 1:
        return s >= 0.5
    s = s.view(k, C, k, C)
    total = None
    for ya in range(k):  # the reference's order: over the x sub-samples of one y sub-sample, then over y
        row = s[ya, :, 0]
        for xb in range(1, k):
            row = row + s[ya, :, xb]
        total = row if total is None else total + row
    return total / (k * k) >= 0.5


# --------------------------------------------------------------------------- the container


@dataclass
class ClassMeta:
    """Per-class metadata (from the COCO category and its carvi extras).

    Attributes:
        name: class name, as the category gives it.
        keypoint_names: ``K`` names.
        flip_pairs: left/right index pairs (inferred from names when the category gives none).
        rigid_keypoints: indices used by SfM only (``None``: all).
        symmetry: ``"none"`` or ``"rotational"``.
        articulated: articulated classes skip mirrored silhouettes in carving.
        category_id: the COCO category id (an int or a string, as the file gives it).
        left_convention: ``"object"`` when a keypoint named left lies on the object's own left
            (Berkeley PASCAL keypoints), ``"viewer"`` when it lies on the left of a frontal photo
            (PASCAL3D+ CAD names). Only used to break close reflection votes in SfM.
        key: the class's folder name in a run's outputs and its key in ``summary.json``: the name
            when it is a safe, unique folder name, else a safe spelling of it
            (:func:`carvi_torch.io.outputs.safe_name`); ``""``: the name itself.
        keypoints_3d: the category's own template, ``K`` points ``[x, y, z]`` (``None`` for an unknown
            one) in its canonical frame, or ``None`` (:mod:`carvi_torch.viewpoints.frame`).
    """

    name: str
    keypoint_names: list
    flip_pairs: list = field(default_factory=list)
    rigid_keypoints: list | None = None
    symmetry: str = "none"
    articulated: bool = False
    category_id: int | str = 0
    left_convention: str = "object"
    key: str = ""
    keypoints_3d: list | None = None

    def __post_init__(self):
        if not self.key:
            self.key = self.name

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoint_names)


@dataclass
class ClassCollection:
    """All instances of one class, as canvas tensors on one device.

    Attributes:
        meta: :class:`ClassMeta`.
        masks: ``(N, C, C)`` bool canvas masks.
        keypoints: ``(N, K, 2)`` float canvas keypoints ``(x, y)`` (undefined where not visible).
        visible: ``(N, K)`` bool.
        canvas_from_image: :class:`Similarity2D` of ``N`` image -> canvas maps.
        image_size: ``(N, 2)`` long ``(width, height)`` of the source images.
        annotation_ids, image_ids: ``N`` ids each, ints or strings as the input gives them.
        object_ids: ``N`` physical-object ids as the input gives them (ints, strings, or ``None``:
            the annotation is its own object).
        object_groups: ``(N,)`` long: instances with equal values are views of one physical object
            (a dense index of ``object_ids``; never surrogates for each other).
        is_mirror: ``(N,)`` bool, True for flipped copies.
        sources: ``N`` strings (where each annotation came from).
        splits: ``N`` strings (``"pool"``, ``"test"`` or ``""``).
        fingerprints: ``N`` strings, a hash of each object's inputs as loaded (its decoded mask, keypoints,
            image entry, ids, class definition; :func:`carvi_torch.io.coco.input_fingerprints`), written with
            its reconstruction so that a rerun resumes an object only when its inputs are unchanged
            (``""``: unknown).
    """

    meta: ClassMeta
    masks: torch.Tensor
    keypoints: torch.Tensor
    visible: torch.Tensor
    canvas_from_image: Similarity2D
    image_size: torch.Tensor
    annotation_ids: list
    image_ids: list
    object_ids: list
    object_groups: torch.Tensor
    is_mirror: torch.Tensor
    sources: list = field(default_factory=list)
    splits: list = field(default_factory=list)
    fingerprints: list = field(default_factory=list)

    def __post_init__(self):
        n = self.masks.shape[0]
        k = self.meta.num_keypoints
        if self.masks.dim() != 3 or self.masks.shape[1] != self.masks.shape[2]:
            raise ValueError(f"masks must be (N, C, C), got {tuple(self.masks.shape)}")
        if self.keypoints.shape != (n, k, 2) or self.visible.shape != (n, k):
            raise ValueError(f"keypoints must be ({n}, {k}, 2) and visible ({n}, {k}); got "
                             f"{tuple(self.keypoints.shape)} and {tuple(self.visible.shape)}")
        self.annotation_ids, self.image_ids = list(self.annotation_ids), list(self.image_ids)
        self.object_ids = list(self.object_ids)
        if not (len(self.annotation_ids) == len(self.image_ids) == len(self.object_ids) == n):
            raise ValueError(f"annotation_ids, image_ids and object_ids must hold N={n} ids each")
        if not self.sources:
            self.sources = [""] * n
        if not self.splits:
            self.splits = [""] * n
        if not self.fingerprints:
            self.fingerprints = [""] * n

    # ---- basics
    def __len__(self) -> int:
        return self.masks.shape[0]

    @property
    def canvas_size(self) -> int:
        return self.masks.shape[-1]

    @property
    def device(self) -> torch.device:
        return self.masks.device

    @property
    def name(self) -> str:
        return self.meta.name

    def _index_list(self, idx) -> list[int]:
        return torch.arange(len(self))[idx].reshape(-1).tolist()

    def _map_rows(self, tensor, rows_of_list, similarity, **changes) -> "ClassCollection":
        """A collection of the same class whose per-row fields are mapped: tensors by ``tensor``, lists (ids,
        sources, ...) by ``rows_of_list``, the canvas similarity by ``similarity``; the fields of ``changes``
        set to them instead."""
        values = dict(changes)
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name in changes:
                continue
            if f.name == "meta":
                values[f.name] = v
            elif isinstance(v, torch.Tensor):
                values[f.name] = tensor(v)
            elif isinstance(v, Similarity2D):
                values[f.name] = similarity(v)
            else:  # a sequence of one value per row (a list, or a tuple as a caller gave it)
                values[f.name] = rows_of_list(v)
        return ClassCollection(**values)

    def __getitem__(self, idx) -> "ClassCollection":
        """Subset by a slice, a list/tensor of indices or a bool mask (always a collection)."""
        if isinstance(idx, int):
            idx = [idx]
        if isinstance(idx, torch.Tensor):
            idx = idx.to("cpu")
        rows = self._index_list(idx)
        ix = torch.tensor(rows, dtype=torch.long, device=self.device)
        return self._map_rows(lambda x: x[ix], lambda values: [values[i] for i in rows], lambda sim: sim[ix])

    def to(self, device) -> "ClassCollection":
        """Move every tensor to ``device``."""
        return self._map_rows(lambda x: x.to(device), list, lambda sim: sim.to(device))

    @staticmethod
    def cat(parts: Sequence["ClassCollection"]) -> "ClassCollection":
        """Concatenate collections of the same class."""
        values = {"meta": parts[0].meta}
        for f in fields(parts[0]):
            if f.name == "meta":
                continue
            got = [getattr(p, f.name) for p in parts]
            if isinstance(got[0], torch.Tensor):
                values[f.name] = torch.cat(got)
            elif isinstance(got[0], Similarity2D):
                values[f.name] = Similarity2D(torch.cat([g.scale for g in got]), torch.cat([g.offset for g in got]))
            else:
                values[f.name] = [v for part in got for v in part]
        return ClassCollection(**values)

    # ---- mirroring
    @property
    def flip_perm(self) -> torch.Tensor:
        """``(K,)`` permutation swapping left/right keypoints."""
        return flip_permutation(self.meta.num_keypoints, self.meta.flip_pairs, device=self.device)

    def mirror(self) -> "ClassCollection":
        """Left-right flipped copies of every instance (``is_mirror`` toggled).

        Masks are flipped along x, keypoints mapped by ``x' = C - 1 - x`` and relabelled along the flip
        pairs, and the canvas similarity describes the flipped image. Mirroring twice is the identity.
        """
        C = self.canvas_size
        perm = self.flip_perm
        kp = self.keypoints[:, perm].clone()
        kp[..., 0] = (C - 1) - kp[..., 0]
        sim = self.canvas_from_image
        off = sim.offset.clone()
        w = self.image_size[:, 0].to(off.dtype)
        off[:, 0] = (C - 1) - sim.scale * (w - 1) - sim.offset[:, 0]
        return self._map_rows(torch.clone, list, None, masks=self.masks.flip(-1), keypoints=kp,
                              visible=self.visible[:, perm], canvas_from_image=Similarity2D(sim.scale.clone(), off),
                              is_mirror=~self.is_mirror)

    def with_mirrors(self) -> "ClassCollection":
        """The originals followed by their mirrored copies (``2N`` instances; copy ``i + N`` mirrors ``i``)."""
        return ClassCollection.cat([self, self.mirror()])

    # ---- conversions
    def keypoints_in_image(self) -> torch.Tensor:
        """``(N, K, 2)`` keypoints mapped back to image pixels (of the flipped image for mirrors)."""
        return self.canvas_from_image.inverse().apply(self.keypoints)

    def num_visible(self) -> torch.Tensor:
        """``(N,)`` number of visible keypoints."""
        return self.visible.sum(dim=1)

    def replace(self, **changes) -> "ClassCollection":
        return replace(self, **changes)
