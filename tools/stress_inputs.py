"""Stress the reconstruct command line with corrupted and hostile inputs, and check every outcome.

    python tools/stress_inputs.py [--work outputs/stress] [--cases PATTERN[,PATTERN...]] [--timeout 120]
                                  [--jobs 2] [--list] [--out-json FILE]

One small valid collection is generated per run (``python -m carvi_torch.datasets procedural``: six
cars, ids 1-6, and six chairs, ids 7-12) into ``WORK/base``. Every case derives its input from it
(the JSON file, ids, categories, images, annotations, whole classes, the command line and config,
damaged outputs of an earlier run, killed runs), runs ``python -m carvi_torch.reconstruct`` on it in
a subprocess (small settings, a timeout, its own folder ``WORK/cases/<case>`` with ``--out`` inside
it) and checks the outcome against the case's expectation, automatically:

- the exit status (0, 1 or 2). 2: exactly one line on stderr, starting ``error:`` and naming the
  problem, and nothing written; 1: the closing ``error:`` line once; 0: no ``error:`` line;
- every bad object named in ``summary.json`` (``input_problems`` or a class's ``failures``) with a
  reason holding the expected phrase; every good object of the file reconstructed (it is in its
  class's ``cameras.json`` and its mesh and voxels load);
- no file created, changed or removed in the case's folder outside ``--out`` (snapshots before and
  after), and no absolute path a hostile name points at;
- no ``Traceback`` on stdout or stderr; no process of the run left running (each case's runs carry
  an environment marker, looked up in ``/proc/*/environ``).

The resume cases copy one finished run of the base collection, damage a file of it and run again
(the damaged object must be redone, every other one resumed); the kill cases send SIGINT (to the
run's process group, as Ctrl-C does), SIGTERM or SIGKILL (to the run alone) once its writer
processes run and a mesh is written, then check that nothing is left running, that every object
with files loads, and that a rerun completes, resuming them.

Prints a markdown table ``case | what is wrong | outcome | good?`` (ready for the README), the run
time, and exits 0 when every case is good, else 1 with the bad cases listed. ``--out-json`` keeps a
record: per case its commands, exit statuses, outcome and what was wrong. Each case's folder and
its runs' stdout/stderr (``WORK/logs``) stay for a look until the next run of the tool.

The ``cmd_`` cases run the other commands (``export``, ``report``, ``evaluate``, ``datasets``) on an output
they cannot write (a file where a folder goes, a folder where a file goes, a folder holding other
files): one ``error:`` line, exit 2, nothing written, as reconstruct's command-line cases.

About 125 cases, 8 minutes with ``--jobs 2`` on 2 cores; every run waits about 2 s for its writer
processes to start, so ``--jobs 4`` keeps 2 cores busier.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import copy
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import trimesh

from carvi_torch.io.layout import finished, object_stem
from carvi_torch.runtime import gone_within, processes_marked

SMALL = ("resolution=16", "proposals=3", "canvas_size=48", "refine_iters=20", "plane_size=24", "preview=false",
         "report=false")
HEAVY = ("resolution=40", "proposals=20")  # a run long enough to be interrupted
#: The interpreter of the commands run: ``-P`` keeps the working folder (a case's folder, which holds its crafted
#: files) off the module search path, where ``python -m`` would put it first, so no module planted there is imported.
PYTHON = (sys.executable, "-P")
RECONSTRUCT = (*PYTHON, "-m", "carvi_torch.reconstruct")
MARKER = "CARVI_STRESS_CASE"
CARS, CHAIRS = tuple(range(1, 7)), tuple(range(7, 13))
ALL = CARS + CHAIRS
DEFAULT_CLI = ("--data", "{data}", "--out", "{out}")
NAN, INF = float("nan"), float("inf")

Edit = Callable[[Any], Any]  # the annotation data -> the new data (most edit it in place and return it)


# --------------------------------------------------------------------------- who a reason must name


@dataclass(frozen=True)
class Src:
    """The object of base annotation ``aid``, found by its ``source`` (for ids that are unusable)."""

    aid: int


@dataclass(frozen=True)
class Cls:
    """A category or class as a whole (a problem without an annotation id)."""

    name: str


@dataclass(frozen=True)
class Lit:
    """A JSON literal written as is (``1e400``, a nesting too deep to build as a Python object)."""

    text: str


# --------------------------------------------------------------------------- edits of the base collection


def _inplace(fn: Callable[[dict], Any]) -> Edit:
    def edit(d):
        fn(d)
        return d
    return edit


def _ann(d: dict, aid) -> dict:
    return next(a for a in d["annotations"] if isinstance(a, dict) and a.get("id") == aid)


def _entry(d: dict, key: str, eid) -> dict:
    return next(e for e in d[key] if e.get("id") == eid)


def chain(*edits: Edit) -> Edit:
    def edit(d):
        for e in edits:
            d = e(d)
        return d
    return edit


def ann(aid, **fields) -> Edit:
    """Set fields of annotation ``aid``."""
    return _inplace(lambda d: _ann(d, aid).update(fields))


def ann_del(aid, *keys) -> Edit:
    return _inplace(lambda d: [_ann(d, aid).pop(k) for k in keys])


def cat(cid, **fields) -> Edit:
    """Set fields of category ``cid`` (1: car, 2: chair)."""
    return _inplace(lambda d: _entry(d, "categories", cid).update(fields))


def cat_del(cid, *keys) -> Edit:
    return _inplace(lambda d: [_entry(d, "categories", cid).pop(k) for k in keys])


def img(iid, **fields) -> Edit:
    return _inplace(lambda d: _entry(d, "images", iid).update(fields))


def img_del(iid, *keys) -> Edit:
    return _inplace(lambda d: [_entry(d, "images", iid).pop(k) for k in keys])


def top(**fields) -> Edit:
    return _inplace(lambda d: d.update(fields))


def top_del(*keys) -> Edit:
    return _inplace(lambda d: [d.pop(k) for k in keys])


def only(ids) -> Edit:
    """Keep only the annotations with these ids."""
    return _inplace(lambda d: d.update(annotations=[a for a in d["annotations"] if a["id"] in ids]))


def append(*entries) -> Edit:
    return _inplace(lambda d: d["annotations"].extend(copy.deepcopy(list(entries))))


def copies(ids, new_id: Callable[[int, int], Any], n: int, **fields) -> Edit:
    """Add ``n`` copies of each annotation in ``ids`` (copy ``j`` of ``aid`` gets id ``new_id(aid, j)``)."""
    def fn(d):
        for aid in ids:
            for j in range(1, n + 1):
                a = copy.deepcopy(_ann(d, aid))
                d["annotations"].append({**a, "id": new_id(aid, j), "source": f"{a['source']}#{j}", **fields})
    return _inplace(fn)


def each_ann(ids, **fields) -> Edit:
    return chain(*(ann(aid, **fields) for aid in ids))


def keypoints(aid, fn: Callable[[list], list]) -> Edit:
    """Replace annotation ``aid``'s flat ``[x, y, v] * K`` list with ``fn(list)``."""
    return _inplace(lambda d: _ann(d, aid).update(keypoints=fn(list(_ann(d, aid)["keypoints"]))))


def triples(flat: list) -> list:
    """``[x, y, v] * K`` as ``[[x, y, v], ...]``."""
    return [flat[i:i + 3] for i in range(0, len(flat), 3)]


def visible(fn: Callable[[float, float, float], tuple], count: int | None = None) -> Callable[[list], list]:
    """A keypoint edit: ``fn(x, y, v)`` -> ``(x, y, v)`` for the first ``count`` visible keypoints."""
    def edit(flat):
        seen = 0
        for i in range(0, len(flat) - 2, 3):
            if flat[i + 2] == 2 and (count is None or seen < count):
                flat[i:i + 3] = fn(*flat[i:i + 3])
                seen += 1
        return flat
    return edit


def segmentation(aid, fn: Callable[[int, int, list], Any]) -> Edit:
    """Replace annotation ``aid``'s segmentation with ``fn(height, width, bbox)``."""
    def fn_(d):
        a = _ann(d, aid)
        im = _entry(d, "images", a["image_id"])
        a["segmentation"] = fn(im["height"], im["width"], a["bbox"])
    return _inplace(fn_)


def _counts_cut(aid) -> Edit:
    """Annotation ``aid``'s compressed RLE counts cut after the last whole run of their first half."""
    def fn(d):
        seg = _ann(d, aid)["segmentation"]
        text = seg["counts"]
        seg["counts"] = text[:max(k for k in range(1, len(text) // 2) if ord(text[k - 1]) - 48 < 32)]
    return _inplace(fn)


def one_pixel(h: int, w: int, bbox: list) -> dict:
    """Uncompressed RLE (column-major) of the one pixel at the centre of ``bbox``."""
    x, y = int(bbox[0] + bbox[2] / 2), int(bbox[1] + bbox[3] / 2)
    k = x * h + y
    return {"size": [h, w], "counts": [k, 1, h * w - k - 1]}


def chairs_named(names: tuple) -> Edit:
    """The chair category renamed ``names[0]``; per further name ``k`` a copy of it (category id ``10 + k``)
    with copies of the chairs (ids ``1000 k + id``)."""
    def fn(d):
        chair = _entry(d, "categories", 2)
        chairs = [a for a in d["annotations"] if a["category_id"] == 2]
        for k, name in enumerate(names[1:], start=1):
            d["categories"].append({**copy.deepcopy(chair), "id": 10 + k, "name": name})
            d["annotations"] += [{**copy.deepcopy(a), "id": 1000 * k + a["id"], "category_id": 10 + k,
                                  "source": f"{a['source']}#{k}"} for a in chairs]
        chair["name"] = names[0]
    return _inplace(fn)


def chairs_ids(names: tuple) -> tuple:
    """The ids of the chairs and their copies that :func:`chairs_named` makes."""
    return CHAIRS + tuple(1000 * k + a for k in range(1, len(names)) for a in CHAIRS)


def string_ids(d: dict) -> dict:
    """Every id a string: ``obj/<id>``, ``img/<id>``, ``cat-<name>``, object_id ``plane <id>``."""
    cats = {c["id"]: f"cat-{c['name']}" for c in d["categories"]}
    for c in d["categories"]:
        c["id"] = cats[c["id"]]
    for i in d["images"]:
        i["id"] = f"img/{i['id']}"
    for a in d["annotations"]:
        a.update(category_id=cats[a["category_id"]], image_id=f"img/{a['image_id']}", object_id=f"plane {a['id']}",
                 id=f"obj/{a['id']}")
    return d


def nested(depth: int) -> Lit:
    return Lit("[" * depth + "]" * depth)


# --------------------------------------------------------------------------- damage to an earlier run's outputs


def _object_file(out: Path, aid: int, kind: str) -> Path:
    return out / ("car" if aid in CARS else "chair") / kind / f"{aid}.{'ply' if kind == 'meshes' else 'npz'}"


def cut(kind: str, aid: int, size: int) -> Callable[[Path], None]:
    def damage(out: Path):
        p = _object_file(out, aid, kind)
        p.write_bytes(p.read_bytes()[:size])
    return damage


def garble(rel: str | tuple) -> Callable[[Path], None]:
    """Replace a file of the run (``"car/cameras.json"``, or ``(kind, aid)``) with garbage."""
    def damage(out: Path):
        p = _object_file(out, rel[1], rel[0]) if isinstance(rel, tuple) else out / rel
        p.write_bytes(b"\x00garbage{[ not what it was " * 20)
    return damage


def remove(kind: str, aid: int) -> Callable[[Path], None]:
    return lambda out: _object_file(out, aid, kind).unlink()


def wrong_voxels(aid: int) -> Callable[[Path], None]:
    def damage(out: Path):
        np.savez(_object_file(out, aid, "voxels"), occupancy=np.ones((2, 2, 2), np.float32), voxel_to_camera=np.eye(3))
    return damage


# --------------------------------------------------------------------------- the cases


@dataclass(frozen=True)
class Case:
    """One hostile input and what the product must do with it.

    ``bad``/``warn``: ``(who, phrase)`` pairs, who an annotation id, :class:`Src`, :class:`Cls` or ``None``
    (any entry): skipped objects (``bad``) or objects named and still reconstructed (``warn``).
    The good objects are the base's annotations the edit left untouched (with their category and
    image), plus ``good``, less ``lost`` and the ids in ``bad``.
    """

    name: str
    what: str
    edit: Edit | None = None
    post: Callable[[bytes], bytes] | None = None  # then an edit of the file's bytes
    cli: tuple = DEFAULT_CLI
    args: tuple = ()
    files: tuple = ()  # (path in the case folder, bytes) made before the run
    rc: int = 0
    error: tuple = ()  # phrases of the one error line (rc 2)
    bad: tuple = ()
    warn: tuple = ()
    good: tuple = ()
    lost: tuple = ()
    absent: tuple = ()  # absolute paths that must not exist afterwards
    out: str = "deep/er/out"  # --out, in the case folder (deep enough that ../../x stays inside it)
    damage: Callable[[Path], None] | None = None  # resume: damage to a finished run, then a rerun
    redo: int = 0  # resume: objects the rerun must make again (the others it must resume)
    kill: int = 0  # a signal sent to a running reconstruct (then a rerun)
    command: str = "reconstruct"  # another command (``cli`` is then its whole command line, exit 2 cases only)
    extra: Callable[[Any, dict], list] | None = None  # more checks: (context, summary) -> problems

    @property
    def family(self) -> str:
        return self.name.split("_")[0]


def _classes_named(names: tuple) -> Callable[[Any, dict], list]:
    """Check: for each name a class folder whose cameras.json names the class so (hostile names kept as given)."""
    def check(ctx, summary):
        found = {_load_json(p).get("class") for p in ctx.out.glob("*/cameras.json")}
        return [f"no class folder for {n!r}" for n in names if n not in found]
    return check


def _file_kept(rel: str, content: bytes) -> Callable[[Any, dict], list]:
    def check(ctx, summary):
        p = ctx.dir / rel
        return [] if p.is_file() and p.read_bytes() == content else [f"{rel} was changed"]
    return check


def _json_cases() -> list[Case]:
    e = ("ann.json",)
    gt_junk = json.dumps({"annotations": {str(a): {"R": "junk", "s": 1, "t": [0, 0]} for a in ALL}}).encode()
    return [
        Case("control_valid", "nothing: the base collection as generated"),
        Case("json_not_json", "a text file, not JSON", post=lambda b: b"images: none\nthis is not json\n", rc=2,
             error=e + ("line 1",)),
        Case("json_empty", "an empty file", post=lambda b: b"", rc=2, error=e),
        Case("json_truncated", "the JSON cut in the middle (a copy that stopped)", post=lambda b: b[: len(b) // 2],
             rc=2, error=e + ("line",)),
        Case("json_list", "a list at the top instead of an object", edit=lambda d: [d], rc=2, error=e),
        Case("json_no_annotations", "no `annotations` key", edit=top_del("annotations"), rc=2,
             error=e + ("annotations",)),
        Case("json_no_categories", "no `categories` key", edit=top_del("categories"), rc=2, error=e + ("categories",)),
        Case("json_annotations_object", "`annotations` is an object", edit=top(annotations={"1": {}}), rc=2,
             error=e + ("annotations",)),
        Case("json_categories_string", "`categories` is a string", edit=top(categories="car,chair"), rc=2,
             error=e + ("categories",)),
        Case("json_images_number", "`images` is a number", edit=top(images=5), rc=2, error=e + ("images",)),
        Case("json_no_images", "no `images` key: no object has an image", edit=top_del("images"), rc=1,
             bad=tuple((a, "unknown image id") for a in ALL)),
        Case("json_no_objects", "an empty `annotations` list: nothing to do", edit=top(annotations=[]), rc=1,
             lost=ALL),
        Case("json_bom", "a UTF-8 byte order mark before the JSON (Windows editors)",
             post=lambda b: b"\xef\xbb\xbf" + b),
        Case("json_latin1", "Latin-1 bytes, not UTF-8 (a supercategory caf\u00e9)",
             edit=cat(1, supercategory="caf\u00e9"),
             post=lambda b: b.replace(b"caf\\u00e9", "caf\u00e9".encode("latin-1")), rc=2, error=e),
        Case("json_huge_sizes", "image width 1e400 (infinite as a float), another's height 10**400",
             edit=chain(img(1, width=Lit("1e400")), img(2, height=10 ** 400)),
             bad=((1, "width/height"), (2, "max_image_pixels"))),
        Case("json_huge_id", "annotation id 10**30 (beyond 64 bits)", edit=ann(3, id=10 ** 30), good=(10 ** 30,)),
        Case("json_huge_coordinate", "a visible keypoint at x=1e308",
             edit=keypoints(4, visible(lambda x, y, v: (1e308, y, v), 1)), warn=((4, "far outside"),), good=(4,)),
        Case("json_nested_100000", "junk nested 100000 deep (beyond any JSON parser's recursion)",
             edit=top(info=nested(100_000)), rc=2, error=e),
        Case("json_gt_garbage", "a gt.json beside the data that is not JSON (cameras=gt not asked for)",
             files=(("gt.json", b"<html>404 Not Found</html>"),)),
        Case("json_gt_list", "a gt.json beside the data holding a list", files=(("gt.json", b"[]"),)),
        Case("json_gt_junk_cameras", "a gt.json beside the data with R \"junk\" for every object",
             files=(("gt.json", gt_junk),)),
    ]


def _id_cases() -> list[Case]:
    unusable = "not an integer or a string"
    lookalikes = ("Obj-A", "obj-a", "a/b", "a_b", "a b")
    odd = ("a\nb", "a\x00b", "x" * 300)
    return [
        Case("id_null", "annotation id null", edit=ann(1, id=None), bad=((Src(1), unusable),)),
        Case("id_float", "annotation id 3.5", edit=ann(1, id=3.5), bad=((Src(1), unusable),)),
        Case("id_bool", "annotation id true", edit=ann(1, id=True), bad=((Src(1), unusable),)),
        Case("id_negative_and_string", "annotation ids -5 and \"car-one\"",
             edit=chain(ann(1, id=-5), ann(2, id="car-one")), good=(-5, "car-one")),
        Case("id_duplicate", "two annotations with id 3", edit=ann(2, id=3), good=(3,),
             bad=((Src(3), "duplicate annotation id"),)),
        Case("id_int_and_string", "ids \"5\" and 5 (equal as text)", edit=ann(1, id="5"), good=("5",),
             bad=((Src(5), "duplicate annotation id"),)),
        Case("id_duplicate_first_skipped", "id 1 twice, the first without a mask: neither is the object",
             edit=chain(ann_del(1, "segmentation"), ann(2, id=1)), lost=(2,),
             bad=((1, "missing mask"), (1, "the first is not reconstructed either"))),
        Case("id_file_name_clash", f"ids \"a/b\" and {object_stem('a/b')!r}, which names a/b's files",
             edit=chain(ann(1, id="a/b"), ann(2, id=object_stem("a/b"))), good=("a/b",),
             bad=((object_stem("a/b"), "name the same output files"),)),
        Case("id_lookalikes", "ids that differ only in case or in a / _ and space: " + ", ".join(lookalikes),
             edit=chain(*(ann(a, id=i) for a, i in zip(CARS, lookalikes))), good=lookalikes),
        Case("id_path", "ids \"../etc/passwd\", \"..\", \"/tmp/abs-id\"",
             edit=chain(ann(1, id="../etc/passwd"), ann(2, id=".."), ann(3, id="/tmp/abs-id")),
             good=("../etc/passwd", "..", "/tmp/abs-id"), absent=("/tmp/abs-id.ply", "/tmp/abs-id.npz")),
        Case("id_control_chars", "ids with a newline, a NUL, 300 characters",
             edit=chain(*(ann(a, id=i) for a, i in zip(CARS, odd))), good=odd),
        Case("id_strings_everywhere", "every id a string (annotation, image, category, object_id)",
             edit=string_ids, good=tuple(f"obj/{a}" for a in ALL)),
        Case("id_equal_as_text", "category_id \"2\" for category 2, image_id \"3\" for image 3",
             edit=chain(ann(7, category_id="2"), ann(3, image_id="3")), good=(7, 3)),
        Case("id_unknown_category", "category_id 99 (no such category)", edit=ann(1, category_id=99),
             bad=((1, "unknown category id"),)),
        Case("id_not_an_object", "annotation entries \"oops\" and 42", edit=append("oops", 42),
             bad=((None, "not an object"),)),
    ]


def _names_case(name: str, what: str, names: tuple) -> Case:
    """The chair category renamed ``names[0]``, and a copy of it (with copies of its objects) per other name."""
    return Case(name, what + ": " + ", ".join(repr(n)[:24] for n in names), edit=chairs_named(names),
                good=chairs_ids(names), absent=("/abs/path",), extra=_classes_named(names))


def _repeat_chair_name(d: dict) -> None:
    """The chair's keypoint 1 named as its keypoint 0."""
    names = _entry(d, "categories", 2)["keypoints"]
    names[1] = names[0]


def _category_cases() -> list[Case]:
    no_names = "no keypoint names"
    return [
        _names_case("cat_names_paths", "classes named like paths", ("../../evil", "/abs/path", "a/b", ".", "..")),
        _names_case("cat_names_odd", "classes named oddly", ("", "ch\x00ir", "ch\nair", "c" * 300,
                                                              "\u6905\u5b50 \U0001fa91")),
        _names_case("cat_names_outputs", "classes named like the run's own files",
                    ("summary.json", "config.yaml", "run.log", "preview.png")),
        _names_case("cat_names_same", "two classes named car, one CAR", ("car", "CAR")),
        Case("cat_name_null", "chair category name null", edit=cat(2, name=None), good=CHAIRS),
        Case("cat_no_keypoints", "chair category without `keypoints`", edit=cat_del(2, "keypoints"),
             bad=((Cls("chair"), no_names),)),
        Case("cat_empty_keypoints", "chair category with `keypoints: []`", edit=cat(2, keypoints=[]),
             bad=((Cls("chair"), no_names),)),
        Case("cat_keypoints_repeat", "chair keypoint 1 renamed as keypoint 0", edit=_inplace(_repeat_chair_name),
             bad=((Cls("chair"), "keypoint names repeat"),)),
        Case("cat_one_keypoint", "chair category with a single keypoint (\"center\")",
             edit=chain(cat(2, keypoints=["center"], flip_pairs=[]),
                        *(keypoints(a, lambda k: next(t for t in triples(k) if t[2] == 2)) for a in CHAIRS)),
             lost=CHAIRS, bad=((Cls("chair"), "no mean shape"),)),
        Case("cat_no_left_right", "chair keypoints named k0..k9: no flip pairs to infer",
             edit=chain(cat_del(2, "flip_pairs"), cat(2, keypoints=[f"k{i}" for i in range(10)])), good=CHAIRS),
        Case("cat_flip_pairs_junk", "flip_pairs [[0, 99]] and \"abc\"",
             edit=chain(cat(1, flip_pairs=[[0, 99]]), cat(2, flip_pairs="abc")), good=ALL,
             warn=((Cls("car"), "invalid flip_pairs"), (Cls("chair"), "invalid flip_pairs"))),
        Case("cat_flip_pairs_overlap", "flip_pairs [[0, 8], [0, 9]] (0 in two pairs) and [[1, 1]]",
             edit=chain(cat(1, flip_pairs=[[0, 8], [0, 9]]), cat(2, flip_pairs=[[1, 1]])), good=ALL,
             warn=((Cls("car"), "invalid flip_pairs"), (Cls("chair"), "invalid flip_pairs"))),
        Case("cat_huge_numbers", "flip_pairs [[10**400, 1]], rigid_keypoints [0, 1, Infinity], keypoints_3d 10**400",
             edit=chain(cat(1, flip_pairs=[[10 ** 400, 1]], rigid_keypoints=[0, 1, Lit("Infinity")]),
                        cat(2, keypoints_3d=[[0, 0, 10 ** 400]] * 10)), good=ALL,
             warn=((Cls("car"), "invalid flip_pairs"), (Cls("car"), "invalid rigid_keypoints"),
                   (Cls("chair"), "keypoints_3d"))),
        Case("cat_rigid_bad", "rigid_keypoints [0, 1] (too few) and [\"x\"]",
             edit=chain(cat(1, rigid_keypoints=[0, 1]), cat(2, rigid_keypoints=["x"])), good=ALL,
             warn=((Cls("car"), "invalid rigid_keypoints"), (Cls("chair"), "invalid rigid_keypoints"))),
        Case("cat_symmetry_bad", "symmetry \"spherical\" and null",
             edit=chain(cat(1, symmetry="spherical"), cat(2, symmetry=None)), good=ALL,
             warn=((Cls("car"), "unknown symmetry"), (Cls("chair"), "unknown symmetry"))),
        Case("cat_extras_junk", "articulated \"maybe\", keypoints_3d \"junk\", left_convention 7",
             edit=cat(1, articulated="maybe", keypoints_3d="junk", left_convention=7), good=CARS),
        Case("cat_unused", "a category nobody uses", edit=_inplace(
            lambda d: d["categories"].append({"id": 3, "name": "bicycle", "keypoints": ["a", "b", "c"]}))),
        Case("cat_entry_junk", "category entries \"car\" and {} beside the real ones",
             edit=_inplace(lambda d: d["categories"].extend(["car", {}])), bad=((None, "without a usable id"),)),
        Case("cat_duplicate_id", "a second category with the chair's id", edit=_inplace(
            lambda d: d["categories"].append({"id": 2, "name": "table", "keypoints": ["a"]})),
             warn=((None, "duplicate category id"),)),
    ]


def _image_cases() -> list[Case]:
    size = "no valid width/height"
    poly = [[10.0, 10.0, 90000.0, 10.0, 90000.0, 90000.0]]
    return [
        Case("img_bad_sizes", "images without width/height, width 0, height -240, width 320.5, width \"320\" "
             "(and one 320.0, fine)",
             edit=chain(img_del(1, "width", "height"), img(2, width=0), img(7, height=-240), img(8, width=320.5),
                        img(3, width="320"), img(9, width=320.0)),
             bad=tuple((a, size) for a in (1, 2, 7, 8, 3)), good=(9,)),
        Case("img_huge", "100000x100000 images, one with a polygon across it, one with an RLE of its size",
             edit=chain(img(1, width=100000, height=100000), ann(1, segmentation=poly),
                        img(7, width=100000, height=100000),
                        ann(7, segmentation={"size": [100000, 100000], "counts": [10 ** 10]})),
             bad=((1, "max_image_pixels"), (7, "max_image_pixels"))),
        Case("img_missing_entry", "the annotation's image entry is missing",
             edit=_inplace(lambda d: d.update(images=[i for i in d["images"] if i["id"] != 1])),
             bad=((1, "unknown image id"),)),
        Case("img_id_junk", "an image entry with id null; another id twice (the second 1x1)",
             edit=chain(img(1, id=None), _inplace(lambda d: d["images"].append({"id": 2, "width": 1, "height": 1}))),
             bad=((1, "unknown image id"), (None, "image entry without a usable id")),
             warn=((None, "duplicate image id"),), good=(2,)),
    ]


def _keypoint_cases() -> list[Case]:
    return [
        Case("ann_kp_shapes", "keypoints one triple short, as [[x, y, v], ...], missing",
             edit=chain(keypoints(1, lambda k: k[:-3]), keypoints(2, triples), ann_del(7, "keypoints")),
             bad=((1, "keypoint values"), (2, "keypoint values"), (7, "no keypoints list"))),
        Case("ann_kp_values", "NaN, Infinity, null and \"abc\" keypoint coordinates (one object each)",
             edit=chain(keypoints(1, visible(lambda x, y, v: (NAN, NAN, v), 2)),
                        keypoints(2, visible(lambda x, y, v: (INF, y, v), 1)),
                        keypoints(7, visible(lambda x, y, v: (None, None, v), 1)),
                        keypoints(8, visible(lambda x, y, v: ("abc", y, v), 1))),
             good=(1, 2, 7), warn=((1, "NaN"), (2, "infinite")), bad=((8, "not numbers"),)),
        Case("ann_kp_none_usable", "every visible keypoint NaN / every keypoint v=0 / every one far outside",
             edit=chain(keypoints(1, visible(lambda x, y, v: (NAN, NAN, v))), keypoints(2, lambda k: [0] * len(k)),
                        keypoints(7, visible(lambda x, y, v: (x + 5000, y - 9000, v)))),
             bad=tuple((a, "no visible keypoint") for a in (1, 2, 7))),
        Case("ann_kp_odd_usable", "two keypoints far outside / visibility 3 / visibility -1 on two",
             edit=chain(keypoints(1, visible(lambda x, y, v: (x + 5000, y, v), 2)),
                        keypoints(7, visible(lambda x, y, v: (x, y, 3))),
                        keypoints(8, visible(lambda x, y, v: (x, y, -1), 2))),
             good=(1, 7, 8), warn=((1, "far outside"),)),
        Case("ann_kp_huge_int", "a keypoint x and a visibility written as 10**400 (beyond float64)",
             edit=chain(keypoints(1, visible(lambda x, y, v: (10 ** 400, y, v), 1)),
                        keypoints(7, visible(lambda x, y, v: (x, y, 10 ** 400), 1))),
             bad=((1, "beyond floating point"), (7, "beyond floating point"))),
        Case("ann_kp_collapsed", "every visible keypoint of one object at one pixel (250, 150)",
             edit=keypoints(2, visible(lambda x, y, v: (250.0, 150.0, v))), bad=((2, "collapse to one point"),)),
    ]


def _mask_cases() -> list[Case]:
    mal = "malformed segmentation"
    return [
        Case("ann_seg_missing", "no `segmentation`; segmentation []", edit=chain(ann_del(1, "segmentation"),
                                                                                ann(7, segmentation=[])),
             bad=((1, "missing mask"), (7, "missing mask"))),
        Case("ann_seg_garbage", "segmentation \"garbage\" and 42", edit=chain(ann(1, segmentation="garbage"),
                                                                            ann(7, segmentation=42)),
             bad=((1, mal), (7, mal))),
        Case("ann_poly_bad", "a polygon not wrapped in a list / of two points / with NaN / of strings",
             edit=chain(ann(1, segmentation=[10, 10, 50, 10, 50, 50]), ann(2, segmentation=[[10, 10, 50, 50]]),
                        ann(7, segmentation=[[10, 10, NAN, 10, 50, 50]]),
                        ann(8, segmentation=[["a", "b", "c", "d", "e", "f"]])),
             bad=((1, mal), (2, mal), (7, "NaN"), (8, mal))),
        Case("ann_rle_bad", "RLE size not the image's / counts summing to 60 / a negative count (right sum)",
             edit=chain(segmentation(1, lambda h, w, b: {"size": [h + 1, w], "counts": [(h + 1) * w]}),
                        segmentation(2, lambda h, w, b: {"size": [h, w], "counts": [10, 20, 30]}),
                        segmentation(7, lambda h, w, b: {"size": [h, w], "counts": [h * w + 5, -5]})),
             bad=((1, "does not match"), (2, "sum to 60"), (7, "non-negative"))),
        Case("ann_rle_garbage", "compressed RLE counts \"!!garbage~~\"",
             edit=segmentation(1, lambda h, w, b: {"size": [h, w], "counts": "!!garbage~~"}),
             bad=((1, "segmentation"),)),
        Case("ann_rle_short", "compressed RLE counts \"\" / cut after their first half (a copy that stopped)",
             edit=chain(segmentation(1, lambda h, w, b: {"size": [h, w], "counts": ""}), _counts_cut(7)),
             bad=((1, "sum to 0"), (7, "sum to"))),
        Case("ann_rle_unicode", "compressed RLE counts with non-ASCII characters",
             edit=segmentation(1, lambda h, w, b: {"size": [h, w], "counts": "\u00e9t\u00e9"}), bad=((1, mal),)),
        Case("ann_mask_empty", "an all-zero RLE; a polygon entirely outside the image",
             edit=chain(segmentation(1, lambda h, w, b: {"size": [h, w], "counts": [h * w]}),
                        ann(7, segmentation=[[1000, 1000, 1100, 1000, 1100, 1100]])),
             bad=((1, "empty mask"), (7, "empty mask"))),
        Case("ann_poly_far", "a polygon vertex at 1e12; a polygon wholly at 1e12",
             edit=chain(ann(1, segmentation=[[0, 0, 1e12, 0, 1e12, 1e12]]),
                        ann(7, segmentation=[[1e12, 1e12, 2e12, 1e12, 2e12, 2e12]])),
             good=(1,), bad=((7, "empty mask"),)),
        Case("ann_mask_odd_usable", "a mask far from the keypoints / covering the image / of one pixel",
             edit=chain(ann(1, segmentation=[[0, 0, 20, 0, 20, 20, 0, 20]]),
                        segmentation(2, lambda h, w, b: {"size": [h, w], "counts": [0, h * w]}),
                        segmentation(7, one_pixel)), good=(1, 2, 7)),
    ]


def _flag_cases() -> list[Case]:
    return [
        Case("ann_flags_no", "truncated \"no\", occluded null, iscrowd 0.0", edit=chain(
            ann(1, truncated="no"), ann(2, occluded=None), ann(7, iscrowd=0.0)), good=(1, 2, 7)),
        Case("ann_flags_yes", "truncated \"yes\"", edit=ann(1, truncated="yes"), bad=((1, "truncated"),)),
        Case("ann_flags_junk", "occluded \"maybe\"; iscrowd 2", edit=chain(ann(1, occluded="maybe"), ann(7, iscrowd=2)),
             bad=((1, "not a yes/no value"), (7, "not a yes/no value"))),
        Case("ann_extras_junk", "bbox \"x\", area -1, source a list, split an object; a 20000-character source",
             edit=chain(ann(1, bbox="x", area=-1, source=["a"], split={"a": 1}, num_keypoints="many"),
                        ann(7, source="line\n" * 4000)), good=(1, 7)),
    ]


def _class_cases() -> list[Case]:
    few = "min_instances"
    return [
        Case("class_of_one", "a class of 1 object", edit=only(CARS + CHAIRS[:1]), lost=CHAIRS,
             bad=((Cls("chair"), few),)),
        Case("class_of_two", "a class of 2 objects", edit=only(CARS + CHAIRS[:2]), lost=CHAIRS,
             bad=((Cls("chair"), few),)),
        Case("class_only_tiny", "the only class has 2 objects: nothing to reconstruct", edit=only(CHAIRS[:2]), rc=1,
             lost=ALL, bad=((Cls("chair"), few),)),
        Case("class_identical", "every chair the same object (six copies of one annotation)",
             edit=chain(only(CARS + (7,)), copies((7,), lambda a, j: 100 + j, 5, object_id=7)),
             good=(7,) + tuple(range(101, 106))),
        Case("class_identical_ids", "six identical chairs, each its own object (no object_id)",
             edit=chain(only(CARS + (7,)), ann(7, object_id=None), copies((7,), lambda a, j: 100 + j, 5)),
             good=(7,) + tuple(range(101, 106))),
        Case("class_one_object_id", "every chair with one object_id", edit=each_ann(CHAIRS, object_id=1), good=CHAIRS),
        Case("class_all_bad", "every chair without a mask", edit=each_ann(CHAIRS, segmentation=None),
             bad=tuple((a, "missing mask") for a in CHAIRS)),
        Case("class_nothing_usable", "every object truncated: nothing to reconstruct", rc=1,
             edit=each_ann(ALL, truncated=True), bad=tuple((a, "truncated") for a in ALL)),
    ]


def _cli_cases() -> list[Case]:
    def err(name, what, args, *phrases, **kw):
        return Case(f"cli_{name}", what, args=args, rc=2, error=phrases, **kw)

    out_file = ("--data", "{data}", "--out", "{dir}/file")
    with_config = DEFAULT_CLI + ("--config", "{dir}/config.yaml")
    return [
        err("device_tpu", "device=tpu", ("device=tpu",), "device"),
        err("device_mps", "device=mps", ("device=mps",), "device"),
        err("device_banana", "device=banana", ("device=banana",), "device"),
        err("unknown_key", "colour=red (no such key)", ("colour=red",), "colour"),
        err("mistyped_key", "resolutoin=16 (a typo)", ("resolutoin=16",), "did you mean 'resolution'"),
        err("no_equals", "a bare word `resolution`", ("resolution",), "resolution"),
        err("resolution_3", "resolution=3", ("resolution=3",), "resolution"),
        err("resolution_5000", "resolution=5000", ("resolution=5000",), "resolution"),
        err("resolution_text", "resolution=abc", ("resolution=abc",), "resolution"),
        err("canvas_5000", "canvas_size=5000", ("canvas_size=5000",), "canvas_size"),
        err("silhouette_nan", "silhouette_weight=nan", ("silhouette_weight=nan",), "silhouette_weight"),
        err("proposals_0", "proposals=0", ("proposals=0",), "proposals"),
        err("seed_negative", "seed=-1", ("seed=-1",), "seed"),
        err("references_unknown", "references=tset (no object has that split)", ("references=tset",),
            "references=tset", "'pool'"),
        err("out_class_file", "a file where the run writes --out/car/meshes", (),
            "car/meshes is a file", files=(("deep/er/out/car/meshes", b"x"),),
            extra=_file_kept("deep/er/out/car/meshes", b"x")),
        Case("cli_out_file", "--out is an existing file", cli=out_file, files=(("file", b"x"),), rc=2,
             error=("is a file",), extra=_file_kept("file", b"x")),
        Case("cli_out_under_file", "--out below an existing file", cli=("--data", "{data}", "--out", "{dir}/file/sub"),
             files=(("file", b"x"),), rc=2, error=("is a file",)),
        Case("cli_data_missing", "--data names no file", cli=("--data", "{dir}/missing.json", "--out", "{out}"),
             rc=2, error=("missing.json",)),
        Case("cli_data_dir", "--data is a folder", cli=("--data", "{dir}/folder", "--out", "{out}"),
             files=(("folder/ann.json", b"{}"),), rc=2, error=("folder",)),
        Case("cli_config_malformed", "--config is malformed YAML", cli=with_config,
             files=(("config.yaml", b"carve:\n  resolution: [16\n x: :\n"),), rc=2, error=("malformed YAML",)),
        Case("cli_config_list", "--config holds a list", cli=with_config,
             files=(("config.yaml", b"- resolution: 16\n- proposals: 3\n"),), rc=2, error=("mapping",)),
        Case("cli_config_unknown_key", "--config with an unknown key", cli=with_config,
             files=(("config.yaml", b"colour: red\n"),), rc=2, error=("colour",)),
        Case("cli_config_missing", "--config names no file", cli=with_config, rc=2, error=("config.yaml",)),
        Case("cli_classes_unknown", "--classes bicycle (no such class)", cli=DEFAULT_CLI + ("--classes", "bicycle"),
             rc=2, error=("'bicycle' is not a class", "its classes: car, chair")),
        Case("cli_out_odd_name", "--out with spaces, unicode and a leading dash", out="deep/er/-out dir \u00e9\u00e8"),
    ]


def _command_cases() -> list[Case]:
    """The other commands' outputs that cannot be written: one ``error:`` line, exit 2, nothing written."""
    run = (("run/summary.json", b'{"classes": {}}'), ("run/config.yaml", b"stage: all\n"))
    file, foreign = (("file", b"x"),), (("mine/notes.txt", b"keep"),)

    def case(command, name, what, cli, files, *phrases):
        return Case(f"cmd_{command}_{name}", what, command=command, cli=cli, files=files, rc=2, error=phrases,
                    extra=_file_kept(files[-1][0], files[-1][1]))

    return [
        case("export", "out_file", "export --out is an existing file", ("--recon", "{dir}/run", "--out", "{dir}/file"),
             run + file, "is a file, not a folder"),
        case("export", "out_under_file", "export --out below an existing file",
             ("--recon", "{dir}/run", "--out", "{dir}/file/sub"), run + file, "Not a directory"),
        case("export", "out_foreign", "export --out holds other files", ("--recon", "{dir}/run", "--out", "{dir}/mine"),
             run + foreign, "not an earlier export"),
        case("report", "out_file", "report --out is an existing file", ("--recon", "{dir}/run", "--out", "{dir}/file"),
             run + file, "is a file"),
        case("report", "out_foreign", "report --out holds other files", ("--recon", "{dir}/run", "--out", "{dir}/mine"),
             run + foreign, "not an earlier report"),
        case("evaluate", "out_file", "evaluate --out is an existing file",
             ("--data", "{data}", "--recon", "{dir}/run", "--out", "{dir}/file"), run + file, "is a file"),
        case("datasets", "procedural_out_file", "datasets procedural --out is an existing file",
             ("procedural", "--out", "{dir}/file"), file, "is a file"),
        case("datasets", "procedural_out_foreign", "datasets procedural --out holds other files",
             ("procedural", "--out", "{dir}/mine"), foreign, "not an earlier synthetic"),
        case("datasets", "voc_out_folder", "datasets voc --out (a file) is a folder",
             ("voc", "--keypoints", "{dir}/mine", "--out", "{dir}/mine"), foreign, "is a folder"),
    ]


def _resume_cases() -> list[Case]:
    return [
        Case("resume_mesh_cut", "a mesh cut to 300 bytes, then a rerun", damage=cut("meshes", 1, 300), redo=1),
        Case("resume_voxels_cut", "a voxel file cut to 200 bytes, then a rerun", damage=cut("voxels", 2, 200),
             redo=1),
        Case("resume_voxels_garbage", "a voxel file replaced by garbage, then a rerun",
             damage=garble(("voxels", 8)), redo=1),
        Case("resume_voxels_wrong", "a voxel file of the wrong kind (float, 3x3 transform)",
             damage=wrong_voxels(9), redo=1),
        Case("resume_mesh_garbage", "a mesh replaced by garbage, then a rerun", damage=garble(("meshes", 3)), redo=1),
        Case("resume_mesh_removed", "a mesh deleted, then a rerun", damage=remove("meshes", 4), redo=1),
        Case("resume_cameras_garbage", "car/cameras.json replaced by garbage, then a rerun",
             damage=garble("car/cameras.json")),
        Case("resume_summary_garbage", "summary.json replaced by garbage, then a rerun",
             damage=garble("summary.json")),
        Case("resume_config_garbage", "config.yaml replaced by garbage, then a rerun", damage=garble("config.yaml")),
    ]


def _kill_cases() -> list[Case]:
    bigger = copies(ALL, lambda a, j: a + 100 * j, 3)
    made = ALL + tuple(a + 100 * j for j in (1, 2, 3) for a in ALL)
    return [
        Case("kill_int", "Ctrl-C (SIGINT to the process group) of a running reconstruct, then a rerun", edit=bigger,
             good=made, kill=signal.SIGINT),
        Case("kill_term", "SIGTERM to a running reconstruct (2 writers), then a rerun", edit=bigger, good=made,
             kill=signal.SIGTERM),
        Case("kill_kill", "SIGKILL to a running reconstruct (2 writers), then a rerun", edit=bigger, good=made,
             kill=signal.SIGKILL),
    ]


CASES = (_json_cases() + _id_cases() + _category_cases() + _image_cases() + _keypoint_cases() + _mask_cases()
         + _flag_cases() + _class_cases() + _cli_cases() + _command_cases() + _resume_cases()
            + _kill_cases())


# --------------------------------------------------------------------------- running a case


@dataclass
class Proc:
    argv: list
    rc: int | None  # None: timed out (killed)
    stdout: str
    stderr: str
    seconds: float


@dataclass
class Ctx:
    """A case's run: its folder, input, output folder and the objects that must come out."""

    case: Case
    dir: Path
    logs: Path
    base: dict
    timeout: float
    good: list = field(default_factory=list)
    marker: str = field(default_factory=lambda: uuid.uuid4().hex)
    runs: list = field(default_factory=list)

    @property
    def data(self) -> Path:
        return self.dir / "ann.json"

    @property
    def out(self) -> Path:
        return self.dir / self.case.out

    def argv(self, extra=()) -> list:
        cli = [a.format(data=self.data, out=self.out, dir=self.dir) for a in self.case.cli]
        if self.case.command != "reconstruct":
            return [*PYTHON, "-m", f"carvi_torch.{self.case.command}", *cli, *self.case.args, *extra]
        return [*RECONSTRUCT, *cli, "--quiet", *SMALL, *self.case.args, *extra]

    def env(self, **extra) -> dict:
        return {**os.environ, MARKER: self.marker, **extra}


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def _dump(data) -> bytes:
    """JSON of the edited data; :class:`Lit` values are written as their literal text."""
    lits: list[str] = []

    def literal(o):
        if isinstance(o, Lit):
            lits.append(o.text)
            return f"@@lit{len(lits) - 1}@@"
        raise TypeError(type(o).__name__)

    text = json.dumps(data, default=literal)
    for i, t in enumerate(lits):
        text = text.replace(f'"@@lit{i}@@"', t, 1)
    return text.encode()


def _good_objects(case: Case, base: dict, data) -> list:
    """The ids that must be reconstructed: untouched base objects (annotation, category and image), the
    case's ``good``, less ``lost`` and the ids it names as bad."""
    auto = []
    if isinstance(data, dict) and all(isinstance(data.get(k), list) for k in ("annotations", "categories", "images")):
        b_ann = {a["id"]: a for a in base["annotations"]}
        cats = {c["id"]: c for c in base["categories"]}
        ims = {i["id"]: i for i in base["images"]}
        d_cats = [c for c in data["categories"] if isinstance(c, dict)]
        d_ims = [i for i in data["images"] if isinstance(i, dict)]
        for a in data["annotations"]:
            aid = a.get("id") if isinstance(a, dict) else None
            if (type(aid) is int and a == b_ann.get(aid) and cats[a["category_id"]] in d_cats
                    and ims[a["image_id"]] in d_ims):
                auto.append(aid)
    named = {str(w) for w, _ in case.bad if not isinstance(w, (Src, Cls)) and w is not None}
    lost = {str(x) for x in case.lost}
    return [g for g in dict.fromkeys(auto + list(case.good)) if str(g) not in named | lost]


def prepare(ctx: Ctx) -> None:
    """The case folder: the annotation file, the case's other files, the folder ``--out`` lies in."""
    if ctx.dir.exists():
        shutil.rmtree(ctx.dir)
    ctx.out.parent.mkdir(parents=True)
    c = ctx.case
    data = (c.edit or (lambda d: d))(copy.deepcopy(ctx.base))
    raw = _dump(data)
    ctx.data.write_bytes(c.post(raw) if c.post else raw)
    for rel, content in c.files:
        (ctx.dir / rel).parent.mkdir(parents=True, exist_ok=True)
        (ctx.dir / rel).write_bytes(content)
    ctx.good = _good_objects(c, ctx.base, data)


def invoke(ctx: Ctx, extra=(), env=None, tag="run", signal_when: Callable[[], bool] | None = None) -> Proc:
    """Run reconstruct in the case folder (stdout/stderr to files outside it); ``signal_when``: send the
    case's signal to it once that returns true."""
    argv = ctx.argv(extra)
    out_f, err_f = ctx.logs / f"{ctx.case.name}.{tag}.out", ctx.logs / f"{ctx.case.name}.{tag}.err"
    t0 = time.perf_counter()
    with open(out_f, "wb") as fo, open(err_f, "wb") as fe:
        p = subprocess.Popen(argv, cwd=ctx.dir, env=ctx.env(**(env or {})), stdout=fo, stderr=fe,
                             start_new_session=True)
        rc = _wait(p, ctx, signal_when)
    proc = Proc(argv, rc, out_f.read_text(errors="replace"), err_f.read_text(errors="replace"),
                time.perf_counter() - t0)
    ctx.runs.append(proc)
    return proc


def _wait(p: subprocess.Popen, ctx: Ctx, signal_when) -> int | None:
    deadline = time.monotonic() + ctx.timeout
    while p.poll() is None and time.monotonic() < deadline:
        if signal_when is not None and signal_when():
            # Ctrl-C reaches a terminal's whole process group (the run's session here); kill, the run alone
            (os.killpg if ctx.case.kill == signal.SIGINT else os.kill)(p.pid, ctx.case.kill)
            signal_when = None
        time.sleep(0.05)
    if p.poll() is None:
        os.killpg(p.pid, signal.SIGKILL)  # the session this tool started for the run
        p.wait()
        return None
    return p.returncode


def marked(marker: str) -> list[int]:
    """Pids of running processes whose environment carries the case's marker."""
    return processes_marked(f"{MARKER}={marker}")


def snapshot(root: Path) -> dict:
    """``{path: (kind, size, mtime)}`` of everything under ``root`` (folders without size and time)."""
    snap = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            st = p.lstat()
            snap[p] = ("dir", 0, 0) if p.is_dir() and not p.is_symlink() else ("file", st.st_size, st.st_mtime_ns)
    return snap


# --------------------------------------------------------------------------- checks


def check_exit(ctx: Ctx, proc: Proc) -> list[str]:
    if proc.rc is None:
        return [f"timed out after {ctx.timeout:.0f} s"]
    return [] if proc.rc == ctx.case.rc else [f"exit status {proc.rc}, expected {ctx.case.rc}"]


def check_streams(ctx: Ctx, proc: Proc) -> list[str]:
    """No traceback; for 2 exactly one line, ``error:`` and the phrases; for 1 the one closing
    ``error:`` line; for 0 none."""
    problems = [f"Traceback on {n}" for n, s in (("stdout", proc.stdout), ("stderr", proc.stderr))
                if "Traceback" in s]
    lines = proc.stderr.strip().splitlines()
    errors = [ln for ln in lines if ln.startswith("error:")]
    if ctx.case.rc == 2:
        if len(lines) != 1 or len(errors) != 1:
            problems.append(f"stderr has {len(lines)} lines, {len(errors)} starting 'error:' (want exactly one)")
        missing = [w for w in ctx.case.error if w not in (errors or [""])[0]]
        problems += [f"the error line does not say {w!r}" for w in missing]
    elif len(errors) != ctx.case.rc:
        problems.append(f"{len(errors)} 'error:' lines on stderr, expected {ctx.case.rc}: {errors[:2]}")
    return problems


def check_writes(ctx: Ctx, before: dict) -> list[str]:
    """Nothing created, changed or removed outside ``--out`` (for exit 2: nothing at all), nor at the
    case's absolute paths."""
    after = snapshot(ctx.dir)
    out = ctx.out if ctx.case.rc != 2 else None
    changed = [p for p in set(before) | set(after)
               if before.get(p) != after.get(p) and not (p in before and p in after and after[p][0] == "dir")]
    outside = sorted(p for p in changed if out is None or not (p == out or out in p.parents))
    problems = [f"{len(outside)} paths written outside --out, e.g. {p.relative_to(ctx.dir)}" for p in outside[:1]]
    return problems + [f"{p} exists" for p in ctx.case.absent if Path(p).exists()]


def check_processes(ctx: Ctx, wait: float = 10.0) -> list[str]:
    """No process of the case's runs left; leftovers are killed (by pid) after being reported."""
    left = gone_within(f"{MARKER}={ctx.marker}", wait)
    return [f"{len(left)} processes of the run still running {wait:.0f} s after it ended"] if left else []


def named_entries(summary: dict) -> list[dict]:
    """Every problem summary.json names: input problems and each class's failures (with the class)."""
    entries = [p for p in summary.get("input_problems", []) if isinstance(p, dict)]
    for key, c in (summary.get("classes") or {}).items():
        entries += [{**f, "class": key, "skipped": True} for f in c.get("failures", [])]
    return entries


def _names(entry: dict, who, sources: dict) -> bool:
    aid = entry.get("annotation_id")
    if who is None:
        return True
    if isinstance(who, Src):
        return entry.get("source") == sources[who.aid]
    if isinstance(who, Cls):
        return aid is None and who.name in (entry.get("category"), entry.get("class"))
    return aid is not None and str(aid) == str(who)


def check_named(ctx: Ctx, summary: dict) -> list[str]:
    """Each expected bad (skipped) and warned (still used) object named with its phrase; every reason
    one line."""
    entries = named_entries(summary)
    sources = {a["id"]: a.get("source") for a in ctx.base["annotations"]}
    problems = []
    for pairs, skipped in ((ctx.case.bad, True), (ctx.case.warn, False)):
        for who, phrase in pairs:
            hits = [e for e in entries if _names(e, who, sources) and phrase in str(e.get("reason"))
                    and bool(e.get("skipped", True)) == skipped]
            if not hits:
                problems.append(f"{_who(who)} not named {'skipped' if skipped else 'with a warning'} for {phrase!r}")
    multi = [e for e in entries if "\n" in str(e.get("reason"))]
    return problems + ([f"a reason of {len(multi)} lines: {multi[0]['reason'][:60]!r}"] if multi else [])


def _who(who) -> str:
    return {Src: lambda w: f"object #{w.aid} (by source)", Cls: lambda w: f"class {w.name!r}"}.get(
        type(who), lambda w: "some entry" if w is None else f"annotation {w!r}")(who)


def made_objects(out: Path) -> dict:
    """``{annotation id as str: class folder}`` of the objects in the classes' cameras.json."""
    made = {}
    for cams in sorted(out.glob("*/cameras.json")):
        for aid in _load_json(cams).get("cameras") or {}:
            made.setdefault(aid, cams.parent)
    return made


def check_good(ctx: Ctx) -> list[str]:
    """Every good object has a camera and a mesh and voxels that load."""
    made = made_objects(ctx.out)
    missing = [g for g in ctx.good if str(g) not in made or finished(made[str(g)], g, "ply") is not True]
    return [f"{len(missing)} good objects not reconstructed: {[str(m)[:20] for m in missing[:5]]}"] if missing else []


def check_outputs(ctx: Ctx, proc: Proc, before: dict) -> tuple[list[str], dict]:
    """Every check of one finished run; returns the problems and summary.json (empty for exit 2)."""
    problems = check_exit(ctx, proc) + check_streams(ctx, proc) + check_writes(ctx, before)
    summary = {}
    if ctx.case.rc != 2:
        summary = _load_json(ctx.out / "summary.json")
        if not summary:
            problems.append("no readable summary.json")
        problems += check_named(ctx, summary) + check_good(ctx)
        problems += [] if (ctx.out / "run.log").is_file() else ["no run.log"]
    elif ctx.out.exists() and ctx.out not in before:  # one made before the run: check_writes saw it unchanged
        problems.append("--out was created")
    if ctx.case.extra is not None:
        problems += ctx.case.extra(ctx, summary)
    return problems + check_processes(ctx), summary


def resumed_counts(summary: dict, redo: int, total: int) -> list[str]:
    classes = (summary.get("classes") or {}).values()
    made = sum(c.get("reconstructed", 0) for c in classes)
    resumed = sum(c.get("resumed", 0) for c in classes)
    if (made, resumed) != (redo, total - redo):
        return [f"the rerun made {made} and resumed {resumed} objects, expected {redo} and {total - redo}"]
    return []


# --------------------------------------------------------------------------- runners


def run_plain(ctx: Ctx, before: dict) -> tuple[list[str], dict]:
    return check_outputs(ctx, invoke(ctx), before)


_SHARED = threading.Lock()


def finished_run(ctx: Ctx) -> Path | str:
    """The output folder of one finished run of the base collection, made by the first resume case that
    needs it (in ``WORK/cases/resume_first``) and copied by every resume case; a string: why there is none."""
    first = Ctx(Case("resume_first", "the finished run the resume cases damage"), ctx.dir.parent / "resume_first",
                ctx.logs, ctx.base, ctx.timeout)
    with _SHARED:
        if not (first.out / "summary.json").is_file():
            prepare(first)
            proc = invoke(first)
            if proc.rc != 0 or check_processes(first):
                return f"the undamaged first run ended with {proc.rc}: {proc.stderr.strip()[-200:]}"
    return first.out


def run_resume(ctx: Ctx, before: dict) -> tuple[list[str], dict]:
    """A finished run's folder, damage to its outputs, then the rerun: the damaged objects redone, the rest
    resumed."""
    first = finished_run(ctx)
    if isinstance(first, str):
        return [first], {}
    shutil.copytree(first, ctx.out)
    ctx.case.damage(ctx.out)
    problems, summary = check_outputs(ctx, invoke(ctx), before)
    return problems + resumed_counts(summary, ctx.case.redo, len(ctx.good)), summary


def _busy(ctx: Ctx) -> Callable[[], bool]:
    """True once the run has a finished mesh and its writer processes: the moment to interrupt it (the
    cheap look at the folder first, so that a loaded machine does not scan /proc every 50 ms meanwhile)."""
    return lambda: any(ctx.out.glob("*/meshes/*.ply")) and len(marked(ctx.marker)) >= 3


def _loads(path: Path) -> bool:
    """Whether an object's voxels (``.npz``) or mesh (``.ply``) file loads."""
    try:
        if path.suffix == ".npz":
            with np.load(path) as z:
                return z["occupancy"].ndim == 3 and z["voxel_to_camera"].shape == (4, 4)
        return len(trimesh.load(path, force="mesh", process=False).faces) > 0
    except Exception:  # noqa: BLE001 - any damage counts
        return False


def intact(out: Path) -> tuple[int, list[str]]:
    """The objects a killed run finished (mesh and voxels), and the files it left that do not load (a
    file is written whole or not at all; an object with one of its two files is merely unfinished)."""
    files = {p: _loads(p) for p in sorted(out.glob("*/meshes/*.ply")) + sorted(out.glob("*/voxels/*.npz"))}
    broken = [str(p.relative_to(out)) for p, ok in files.items() if not ok]
    kinds = {}
    for p, ok in files.items():
        kinds.setdefault((p.parent.parent, p.stem), []).append(ok)
    done = sum(oks == [True, True] for oks in kinds.values())
    return done, ([f"files that do not load after the kill: {broken[:4]}"] if broken else [])


def run_kill(ctx: Ctx, before: dict) -> tuple[list[str], dict]:
    """Signal a running reconstruct once its writers run and a mesh is out; nothing may be left running,
    the finished objects must load, and a rerun completes (resuming them)."""
    env = {"CARVI_WRITERS": "2"}
    killed = invoke(ctx, HEAVY, env, tag="killed", signal_when=_busy(ctx))
    problems = [] if killed.rc not in (None, 0) else [f"the run was not interrupted (exit {killed.rc})"]
    problems += [f"Traceback after the signal on {n}" for n, s in (("stdout", killed.stdout),
                                                                    ("stderr", killed.stderr)) if "Traceback" in s]
    problems += check_processes(ctx)
    done, broken = intact(ctx.out)
    rest, summary = check_outputs(ctx, invoke(ctx, HEAVY, env), before)
    resumed = sum(c.get("resumed", 0) for c in (summary.get("classes") or {}).values())
    low = [f"the rerun resumed {resumed} objects, the killed run had finished {done}"] if resumed < done else []
    return problems + broken + rest + low, summary


def run_case(case: Case, base: dict, work: Path, timeout: float) -> dict:
    ctx = Ctx(case, work / "cases" / case.name, work / "logs", base, timeout)
    t0 = time.perf_counter()
    try:
        prepare(ctx)
        before = snapshot(ctx.dir)
        runner = run_kill if case.kill else run_resume if case.damage else run_plain
        problems, summary = runner(ctx, before)
    except Exception as e:  # noqa: BLE001 - a broken case is reported as one, the others go on
        problems, summary = [f"the tool failed on this case: {type(e).__name__}: {e}"], {}
    return {"case": case.name, "family": case.family, "what": case.what, "expected_exit": case.rc,
            "exit": [r.rc for r in ctx.runs], "outcome": outcome(ctx, summary), "good": not problems,
            "problems": problems, "seconds": round(time.perf_counter() - t0, 2),
            "commands": [shlex.join(map(str, r.argv)) for r in ctx.runs],
            "stderr_tail": ctx.runs[-1].stderr[-600:] if ctx.runs else ""}


def status(rc: int | None) -> str:
    if rc is None:
        return "timed out"
    return f"killed by {signal.Signals(-rc).name}" if rc < 0 else f"exit {rc}"


def outcome(ctx: Ctx, summary: dict) -> str:
    """One line: the runs' exit statuses, the last one's error line (or the last line it wrote) or the
    objects made, and the first expected reason named."""
    if not ctx.runs:
        return "not run"
    last = ctx.runs[-1]
    head = " then ".join(status(r.rc) for r in ctx.runs)
    if last.rc == 2 or not summary:
        lines = last.stderr.strip().splitlines()
        raised = [ln for ln in lines if not ln.startswith(" ") and ("Error" in ln or "Interrupt" in ln)]
        said = ([ln for ln in lines if ln.startswith("error:")] or raised[-1:] or [""])[0]
        return f"{head}: {said}".replace(str(ctx.dir) + "/", "")[:110].rstrip(": ")
    classes = (summary.get("classes") or {}).values()
    text = f"{head}; {sum(c.get('reconstructed', 0) + c.get('resumed', 0) for c in classes)} objects"
    resumed = sum(c.get("resumed", 0) for c in classes)
    text += f" ({resumed} resumed)" if resumed else ""
    sources = {a["id"]: a.get("source") for a in ctx.base["annotations"]}
    hits = [e for who, phrase in ctx.case.bad + ctx.case.warn for e in named_entries(summary)
            if _names(e, who, sources) and phrase in str(e.get("reason"))]
    failed = [f"{k}: {c['failures'][0]['reason']}" for k, c in (summary.get("classes") or {}).items()
              if c.get("status") == "failed" and c.get("failures")]
    said = str(hits[0]["reason"]) if hits else failed[0] if failed else ""
    return text + (f"; \"{said[:70]}\"" if said else "")


# --------------------------------------------------------------------------- the command line


def make_base(work: Path) -> dict:
    """The valid collection every case starts from (checked to be the one the cases are written for)."""
    base = work / "base"
    if base.exists():
        shutil.rmtree(base)
    cmd = [*PYTHON, "-m", "carvi_torch.datasets", "procedural", "--out", str(base), "--instances", "6",
           "--classes", "car,chair", "--seed", "1", "--quiet"]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    data = json.loads((base / "annotations.json").read_text())
    layout = sorted((a["id"], a["category_id"]) for a in data["annotations"])
    if layout != [(a, 1 if a in CARS else 2) for a in ALL]:
        raise SystemExit(f"error: the base collection is not six cars (ids 1-6) and six chairs (7-12): {layout}")
    return data


def cell(text) -> str:
    """A markdown table cell: one line, pipes escaped, unprintable characters shown as ?."""
    return "".join(ch if ch.isprintable() else "?" for ch in str(text)).replace("|", "\\|")


def table(results: list[dict]) -> str:
    rows = ["| case | what is wrong | outcome | good? |", "|---|---|---|---|"]
    for r in results:
        verdict = "yes" if r["good"] else "**NO**: " + "; ".join(r["problems"])
        rows.append(f"| `{r['case']}` | {cell(r['what'])} | {cell(r['outcome'])} | {cell(verdict)} |")
    return "\n".join(rows)


def select(patterns: str | None) -> list[Case]:
    wanted = [p for p in (patterns or "").split(",") if p]
    return [c for c in CASES if not wanted or any(p in c.name for p in wanted)]


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python tools/stress_inputs.py",
                                 description="Run reconstruct on corrupted and hostile inputs and check that each "
                                             "outcome is the promised one (exit status, error line, named bad "
                                             "objects, good objects made, nothing written outside --out, no "
                                             "traceback, no process left).")
    ap.add_argument("--work", default="outputs/stress", help="work folder (base collection, cases, logs)")
    ap.add_argument("--cases", help="only the cases whose name holds one of these comma-separated substrings")
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds per reconstruct run (default 120)")
    ap.add_argument("--jobs", type=int, default=2, help="cases run in parallel (default 2)")
    ap.add_argument("--list", action="store_true", help="list the cases and exit")
    ap.add_argument("--out-json", help="write the record of the run here")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:  # started in the background (nohup, `&` in a script):
        signal.signal(signal.SIGINT, signal.default_int_handler)  # the runs start with the default, as from a shell
    args = parse_args(argv)
    cases = select(args.cases)
    if args.list:
        print("\n".join(f"{c.name:28s} {c.what}" for c in cases))
        return 0
    if not cases:
        print(f"error: no case matches {args.cases!r} (see --list)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    work = Path(args.work).resolve()
    for sub in ("cases", "logs"):
        shutil.rmtree(work / sub, ignore_errors=True)
    (work / "logs").mkdir(parents=True)
    base = make_base(work)
    with cf.ThreadPoolExecutor(max(1, args.jobs)) as pool:
        results = list(pool.map(lambda c: run_case(c, base, work, args.timeout), cases))
    seconds = time.perf_counter() - t0
    print(table(results))
    bad = [r["case"] for r in results if not r["good"]]
    print(f"\n{len(results)} cases, {len(results) - len(bad)} good, {len(bad)} bad; {seconds:.0f} s "
          f"with {args.jobs} jobs")
    if args.out_json:
        Path(args.out_json).write_text(json.dumps({"seconds": round(seconds, 1), "jobs": args.jobs,
                                                   "cases": results}, indent=1, default=str))
    if bad:
        print("bad cases: " + ", ".join(bad), file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
