"""PASCAL VOC class metadata: ids, groups and keypoint-name patterns.

A plain table, kept apart from the converter (:mod:`carvi_torch.io.voc`) so that it
can be read and changed on its own.

* Category ids are the VOC class indices: ``aeroplane`` is 1, ..., ``tvmonitor`` is 20
  (the order of :data:`VOC_CLASSES`, the order of SBD's ``GTinst.Categories`` and of
  the VOC ``SegmentationClass`` palette indices).
* ``symmetry`` is ``"rotational"`` for :data:`ROTATIONAL_CLASSES`, else ``"none"``.
* ``articulated`` is true for :data:`ARTICULATED_CLASSES`.
* The rigid keypoint subset used by rigid SfM (paper, Sec. 3.1) is chosen by name
  patterns, so it works with any name list (the Berkeley names, or a user's):

  - :data:`HEAD_TORSO_CLASSES` (the animals and person) keep head and torso
    keypoints only. A name is kept when none of its words is a limb word
    (:data:`LIMB_WORDS`: elbow, knee, paw, hoof, wing, leg, foot, ankle, wrist, ...)
    and one of its words is a head/torso word (:data:`HEAD_TORSO_WORDS`: eye, ear,
    nose, muzzle, throat, withers, neck, beak, head, shoulder, hip, ...) or it names the
    tail base (the word ``tail`` together with ``base`` / ``root``, or ``tailbase``).
    Berkeley cat: ``L_EarBase, L_Eye, Nose, R_EarBase, R_Eye, TailBase, Throat,
    Withers``; bird: ``Beak_Base, Beak_Tip, Left_Eye, Lower_Neck_Base, Right_Eye,
    Upper_Neck_Base`` (wings, ``Leg_Center`` and ``Tail_Tip`` are left out).
  - :data:`HULL_CLASSES` (boat) keep every keypoint with no rigging word
    (:data:`RIGGING_WORDS`: sail, mast, boom, ...): the hull.
  - When a pattern keeps fewer than :data:`MIN_RIGID_KEYPOINTS` names (too few for a
    rigid 3-D shape), all keypoints are used instead.

"Words" are the parts of a name split at ``_``, ``-``, spaces, dots, digits and
camel-case boundaries, lower-cased: ``L_EarBase`` -> ``l, ear, base``.
"""
from __future__ import annotations

import re

__all__ = [
    "VOC_CLASSES",
    "SUPERCATEGORY",
    "ROTATIONAL_CLASSES",
    "ARTICULATED_CLASSES",
    "HEAD_TORSO_CLASSES",
    "HULL_CLASSES",
    "HEAD_TORSO_WORDS",
    "LIMB_WORDS",
    "TAIL_BASE_WORDS",
    "RIGGING_WORDS",
    "MIN_RIGID_KEYPOINTS",
    "normalize_class_name",
    "category_id",
]

#: The 20 PASCAL VOC classes in VOC index order (category id = position + 1).
VOC_CLASSES: tuple[str, ...] = (
    "aeroplane", "bicycle", "bird", "boat", "bottle",
    "bus", "car", "cat", "chair", "cow",
    "diningtable", "dog", "horse", "motorbike", "person",
    "pottedplant", "sheep", "sofa", "train", "tvmonitor",
)

#: COCO ``supercategory`` of each class.
SUPERCATEGORY: dict[str, str] = {
    **{c: "vehicle" for c in ("aeroplane", "bicycle", "boat", "bus", "car", "motorbike", "train")},
    **{c: "animal" for c in ("bird", "cat", "cow", "dog", "horse", "sheep")},
    "person": "person",
    **{c: "indoor" for c in ("bottle", "chair", "diningtable", "pottedplant", "sofa", "tvmonitor")},
}

#: Classes reconstructed with rotational-symmetry surrogates.
ROTATIONAL_CLASSES = frozenset({"bottle", "diningtable", "pottedplant"})

#: Articulated classes (no mirrored silhouettes in carving).
ARTICULATED_CLASSES = frozenset({"bird", "cat", "cow", "dog", "horse", "sheep", "person"})

#: Classes whose rigid subset is head + torso (limbs articulate).
HEAD_TORSO_CLASSES = frozenset({"bird", "cat", "cow", "dog", "horse", "sheep", "person"})

#: Classes whose rigid subset is the hull (sails and masts are absent on motor boats).
HULL_CLASSES = frozenset({"boat"})

#: Words of head and torso keypoints.
HEAD_TORSO_WORDS = frozenset({
    "eye", "eyes", "ear", "ears", "earbase", "nose", "muzzle", "snout", "mouth", "lip", "lips",
    "jaw", "chin", "cheek", "throat", "withers", "neck", "nape", "beak", "bill", "head", "crown",
    "forehead", "horn", "horns", "shoulder", "shoulders", "hip", "hips", "chest", "breast",
    "belly", "spine", "rump", "torso", "body", "pelvis", "tailbase",
})

#: Words of limb keypoints (never rigid, even with a head/torso word).
LIMB_WORDS = frozenset({
    "elbow", "elbows", "knee", "knees", "paw", "paws", "hoof", "hooves", "wing", "wings",
    "leg", "legs", "foot", "feet", "ankle", "ankles", "wrist", "wrists", "toe", "toes",
    "claw", "claws", "hock", "fetlock", "arm", "arms", "hand", "hands", "finger", "fingers",
    "thigh", "shin", "heel",
})

#: Words that, together with ``tail``, name the tail base (torso); other tail points are not rigid.
TAIL_BASE_WORDS = frozenset({"base", "root", "start"})

#: Words of boat rigging keypoints (not part of the hull).
RIGGING_WORDS = frozenset({"sail", "sails", "mast", "masts", "boom", "flag", "rigging", "spar"})

#: Fewest names a pattern must keep; below it the whole keypoint list is rigid.
MIN_RIGID_KEYPOINTS = 4

_ALIASES = {"airplane": "aeroplane", "plane": "aeroplane", "bike": "bicycle", "motorcycle": "motorbike",
            "table": "diningtable", "plant": "pottedplant", "tv": "tvmonitor", "monitor": "tvmonitor",
            "couch": "sofa"}


def normalize_class_name(name: str) -> str | None:
    """The VOC class a category name refers to, or ``None``.

    Case, spaces, ``_``, ``-`` and ``/`` are ignored, and a few common aliases are
    accepted: ``"Potted Plant"`` -> ``"pottedplant"``, ``"tv/monitor"`` ->
    ``"tvmonitor"``, ``"airplane"`` -> ``"aeroplane"``.

    Example:
        >>> normalize_class_name("Dining Table"), normalize_class_name("unicorn")
        ('diningtable', None)
    """
    if not isinstance(name, str):
        return None
    key = re.sub(r"[\s_\-/]+", "", name).lower()
    key = _ALIASES.get(key, key)
    return key if key in VOC_CLASSES else None


def category_id(name: str) -> int:
    """VOC category id (1..20) of a class name (normalised with :func:`normalize_class_name`).

    Raises:
        ValueError: ``name`` is not a VOC class.
    """
    key = normalize_class_name(name)
    if key is None:
        raise ValueError(f"name: {name!r} is not a PASCAL VOC class (one of {', '.join(VOC_CLASSES)})")
    return VOC_CLASSES.index(key) + 1
