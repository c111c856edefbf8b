"""Meshes with 3-D semantic keypoints: loading, and left/right keypoint pairs from names.

Two on-disk forms are read (CPU-side; files are parsed with numpy / trimesh):

* the PASCAL3D+ ``.npz`` files (``vertices (V,3)``, ``faces (F,3)`` 0-based,
  ``keypoint_names (K,)``, ``keypoints (K,3)``); the class is the file stem without
  its digits (``aeroplane01.npz`` -> ``aeroplane``);
* any mesh trimesh reads (``X.ply``, ``.obj``, ``.off``, ``.stl``, ``.glb``) with a
  ``X.json`` beside it: ``{"class": "car", "keypoints": {"name": [x, y, z], ...}}``.
  A scene (``.glb``) is flattened into one mesh.

Object frame (as PASCAL3D+): +z up, the object's front towards -y, unit-ish size.
Real data is messy: meshes are rarely watertight and keypoint sets differ between
models of one class; both are kept as they are (a name a model lacks is simply absent
from its ``keypoint_names``). Only unusable entries are dropped, with a warning naming
the file: non-finite keypoints and repeated keypoint names (in a ``.json`` a key given
twice, in an ``.npz`` a name repeated: the first is kept).

A model the renders cannot use is refused whole, with a one-line reason naming its file
(:class:`BadModelFile`; :func:`load_models` skips it with a warning and reads the rest): a
file no reader understands, a malformed or misshapen keypoint file, non-finite vertices, a
mesh without faces or without extent (every vertex at one point, every triangle flat), no
keypoints at all, or keypoints far outside the mesh (:data:`KEYPOINT_OFF_MESH_MAX`: in other
units than the mesh). Sizes are judged relative to the mesh, so a model in any unit renders alike.

Left and right are not always named alike across a class's models: PASCAL3D+'s motorbike01
names its handlebar ends from the other side than the other three motorbikes. A human
annotator of its photographs would name them like the others, so :func:`load_models`
exchanges such a pair's names (:func:`harmonize_sides`, with a warning naming the model);
``sides="as-given"`` keeps the names as stored.
"""
from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch

from ..collection import infer_flip_pairs  # re-exported: name-based left/right pairs
from ..io.outputs import read_json, shown_names

__all__ = ["Model", "BadModelFile", "MESH_SUFFIXES", "KEYPOINT_OFF_MESH_MAX", "SIDE_VOTE_MIN", "side_disagreements",
           "turned_models", "harmonize_sides", "side_swaps_of",
           "load_cad_npz", "load_mesh_with_keypoints", "load_model", "load_models",
           "infer_flip_pairs", "category_from_stem"]

#: File suffixes read through trimesh (a ``.json`` with the keypoints must sit beside the mesh).
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf")

#: A keypoint farther than this fraction of the mesh's bounding-box diagonal outside that box refuses the model
#: (PASCAL3D+'s keypoints lie within 2% of the diagonal from the surface): keypoints in other units than the
#: mesh (millimetres on a mesh in metres) would put the mesh, framed with its keypoints, in a corner of the view.
KEYPOINT_OFF_MESH_MAX = 0.25


class BadModelFile(ValueError):
    """A model file (or its keypoint file) that cannot be rendered; the message, one line, names the file."""


@dataclass
class Model:
    """A mesh in its object frame with named 3-D keypoints.

    Attributes:
        name: unique model name (file stem, e.g. ``"aeroplane01"``).
        category: class name (e.g. ``"aeroplane"``).
        vertices: ``(V, 3)`` float32, object frame (+z up, front towards -y).
        faces: ``(F, 3)`` int64 (long) vertex indices, 0-based.
        keypoint_names: ``K`` names, unique.
        keypoints: ``(K, 3)`` float32 keypoint positions in the object frame.
        source: the file the model was read from (its name only), or a label for
            generated models; written as the annotations' ``source``.
        side_swaps: left/right name pairs exchanged on loading (:func:`harmonize_sides`), each
            ``(name, name)`` sorted; empty when the names are as stored.

    Raises:
        ValueError: naming the model: arrays of other shapes, faces that are not integers or index outside
            the vertices, non-finite vertices or keypoints (also values beyond float32), repeated names.
    """

    name: str
    category: str
    vertices: torch.Tensor
    faces: torch.Tensor
    keypoint_names: list[str] = field(default_factory=list)
    keypoints: torch.Tensor = field(default_factory=lambda: torch.zeros(0, 3))
    source: str = ""
    side_swaps: list[tuple[str, str]] = field(default_factory=list)

    def __post_init__(self):
        self.vertices = torch.as_tensor(self.vertices, dtype=torch.float32)
        faces = torch.as_tensor(self.faces)
        if faces.dtype == torch.bool or (faces.is_floating_point() and not bool((faces == faces.round()).all())):
            raise ValueError(f"{self.name}: faces must be integer vertex indices, got "
                             f"{'booleans' if faces.dtype == torch.bool else 'fractions'}")
        self.faces = faces.to(torch.long)
        self.keypoints = torch.as_tensor(self.keypoints, dtype=torch.float32)
        if self.keypoints.numel() == 0:
            self.keypoints = self.keypoints.reshape(0, 3)
        self.keypoint_names = [str(n) for n in self.keypoint_names]
        if self.vertices.dim() != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"{self.name}: vertices must be (V, 3), got {tuple(self.vertices.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"{self.name}: faces must be (F, 3), got {tuple(self.faces.shape)}")
        if self.keypoints.dim() != 2 or self.keypoints.shape[1] != 3:
            raise ValueError(f"{self.name}: keypoints must be (K, 3), got {tuple(self.keypoints.shape)}")
        for what, x in (("vertices", self.vertices), ("keypoints", self.keypoints)):
            if not bool(torch.isfinite(x).all()):
                raise ValueError(f"{self.name}: {what} hold non-finite coordinates (NaN, or beyond float32's range)")
        if self.faces.numel() and (int(self.faces.min()) < 0 or int(self.faces.max()) >= self.vertices.shape[0]):
            raise ValueError(f"{self.name}: faces index outside [0, {self.vertices.shape[0]})")
        if len(self.keypoint_names) != self.keypoints.shape[0]:
            raise ValueError(f"{self.name}: {len(self.keypoint_names)} keypoint names for "
                             f"{self.keypoints.shape[0]} keypoints")
        if len(set(self.keypoint_names)) != len(self.keypoint_names):
            raise ValueError(f"{self.name}: keypoint names are not unique")

    @property
    def bounding_radius(self) -> float:
        """Largest distance of a vertex from the object-frame origin (object units)."""
        if self.vertices.shape[0] == 0:
            return 0.0
        return float(self.vertices.norm(dim=1).max())

    def keypoint_dict(self) -> dict[str, list[float]]:
        """``{name: [x, y, z]}`` (the JSON form read by :func:`load_mesh_with_keypoints`)."""
        return {n: [float(v) for v in p] for n, p in zip(self.keypoint_names, self.keypoints.tolist())}

    def to_trimesh(self):
        """The mesh as a ``trimesh.Trimesh`` (``process=False``: vertices and faces kept as they are)."""
        import trimesh

        return trimesh.Trimesh(self.vertices.numpy().astype(np.float64), self.faces.numpy(), process=False)


# --------------------------------------------------------------------------- left and right

#: A left/right pair votes on which side its first name lies when its two points are at least this
#: fraction of the model's width (x extent) apart along x, the PASCAL3D+ frame's left-right axis.
SIDE_VOTE_MIN = 0.1


def _pair_sides(model: Model) -> dict[tuple[str, str], int]:
    """``{(a, b): sign of x_a - x_b}`` for the model's left/right pairs (``a < b``) that vote.

    Example:
        >>> box = torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]])
        >>> kp = torch.tensor([[0.5, 0, 0], [-0.5, 0, 0], [0.05, 0, 0], [-0.05, 0, 0]])
        >>> _pair_sides(Model("m", "m", box, torch.zeros(0, 3), ["right_a", "left_a", "left_b", "right_b"], kp))
        {('left_a', 'right_a'): -1}
    """
    names, x = model.keypoint_names, model.keypoints[:, 0].double()
    width = float(model.vertices[:, 0].max() - model.vertices[:, 0].min()) if len(model.vertices) else 0.0
    sides = {}
    for i, j in infer_flip_pairs(names):
        (a, ia), (b, ib) = sorted([(names[i], i), (names[j], j)])
        dx = float(x[ia] - x[ib])
        if width > 0 and abs(dx) >= SIDE_VOTE_MIN * width:
            sides[(a, b)] = 1 if dx > 0 else -1
    return sides


def _class_votes(models: Sequence[Model]) -> list[dict[tuple[str, str], tuple[bool, int]]]:
    """Per model, ``{pair: (named like the class, how many other models decide)}`` for the pairs that at
    least two other models of its class have and all put on one side (:func:`_pair_sides`)."""
    sides = [_pair_sides(m) for m in models]
    votes = []
    for k, model in enumerate(models):
        mine = {}
        for pair, sign in sides[k].items():
            others = [s[pair] for o, s in enumerate(sides)
                      if o != k and models[o].category == model.category and pair in s]
            if len(others) >= 2 and len(set(others)) == 1:
                mine[pair] = (others[0] == sign, len(others))
        votes.append(mine)
    return votes


def side_disagreements(models: Sequence[Model]) -> list[tuple[int, tuple[str, str], int]]:
    """Left/right pairs a model names from the other side than every other model of its class.

    A pair counts when at least two other models of the class have it and all of them put its
    first name on the other side of x than this model does (each pair judged by its x
    separation, at least :data:`SIDE_VOTE_MIN` of the model's width), and when at least one
    other pair of the model is named like the class: a model whose every such pair disagrees is
    turned in its frame rather than misnamed (:func:`turned_models`).

    Returns:
        ``(model index, (name, name) sorted, how many other models agree)`` in model order.

    Example:
        >>> kp = lambda a, b: torch.tensor([[a, 0.0, 0.0], [-a, 0.0, 0.0], [b, 0.0, 0.0], [-b, 0.0, 0.0]])
        >>> box = torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]])
        >>> names = ["left_a", "right_a", "left_b", "right_b"]
        >>> ms = [Model(f"m{i}", "m", box, torch.zeros(0, 3), names, kp(*x))
        ...       for i, x in enumerate([(-0.8, -0.5), (-0.7, -0.6), (0.9, -0.5)])]
        >>> side_disagreements(ms)
        [(2, ('left_a', 'right_a'), 2)]
    """
    return _disagreements(_class_votes(models))


def turned_models(models: Sequence[Model]) -> list[int]:
    """Indices of the models whose every pair that the class decides (:func:`side_disagreements`) lies
    on the other side of x: most likely turned in their frame (front not towards -y), not misnamed."""
    return _turned(_class_votes(models))


def _disagreements(votes: list[dict]) -> list[tuple[int, tuple[str, str], int]]:
    """:func:`side_disagreements` from :func:`_class_votes`."""
    found = []
    for k, mine in enumerate(votes):
        if any(agree for agree, _ in mine.values()):
            found += [(k, pair, n) for pair, (agree, n) in mine.items() if not agree]
    return found


def _turned(votes: list[dict]) -> list[int]:
    """:func:`turned_models` from :func:`_class_votes`."""
    return [k for k, mine in enumerate(votes) if mine and not any(a for a, _ in mine.values())]


def harmonize_sides(models: Sequence[Model], warn: bool = True) -> list[Model]:
    """The models with every pair of :func:`side_disagreements` named like the rest of the class.

    The two names of such a pair are exchanged on that model (its points stay where they are), and
    ``side_swaps`` lists them; a warning names the model and the pair when ``warn``, and each model
    of :func:`turned_models` (kept as it is). Models without a swap are returned as they are.
    """
    votes = _class_votes(models)  # once, for both tests
    swaps: dict[int, list[tuple[str, str]]] = {}
    for k, pair, agree in _disagreements(votes):
        swaps.setdefault(k, []).append(pair)
        if warn:
            warnings.warn(f"{models[k].name}: {pair[0]!r} and {pair[1]!r} exchanged: the {agree} other "
                          f"{models[k].category} models that have them name them from the other side", stacklevel=3)
    for k in _turned(votes) if warn else []:
        warnings.warn(f"{models[k].name}: every left/right pair lies on the other side of x than on the other "
                      f"{models[k].category} models: is it turned in its frame (front towards -y)? names kept",
                      stacklevel=3)
    out = list(models)
    for k, pairs in swaps.items():
        rename = {a: b for p in pairs for a, b in (p, p[::-1])}
        out[k] = replace(models[k], keypoint_names=[rename.get(n, n) for n in models[k].keypoint_names],
                         side_swaps=models[k].side_swaps + pairs)
    return out


def side_swaps_of(models: Sequence[Model]) -> dict[str, list[list[str]]]:
    """``{model name: [[name, name], ...]}`` of the models with renamed pairs (``side_swaps``), the form
    a rendered dataset records in its ``info`` (:func:`~carvi_torch.synthetic.render.render_dataset`)."""
    return {m.name: [list(p) for p in m.side_swaps] for m in models if getattr(m, "side_swaps", None)}


# --------------------------------------------------------------------------- loading


def category_from_stem(stem: str) -> str:
    """Class name of a model file stem: the stem without digits (and trailing ``_``/``-``).

    Example:
        >>> category_from_stem("aeroplane01"), category_from_stem("car_3")
        ('aeroplane', 'car')
    """
    cat = re.sub(r"\d+", "", stem).strip("_- .")
    if not cat:
        raise ValueError(f"model file stem {stem!r}: cannot derive a class name (no letters)")
    return cat


def _reason(e: BaseException) -> str:
    """An exception as one short line: its message (else its type's name), whitespace folded, cut at 160 characters."""
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def _clean_keypoints(names: Sequence[str], points: np.ndarray, where: str) -> tuple[list[str], np.ndarray]:
    """Drop non-finite and repeated keypoints (with a warning naming ``where``); ``points`` must be ``(K, 3)`` for
    the ``K`` names (else :class:`BadModelFile`)."""
    names = [str(n) for n in names]
    points = np.asarray(points, dtype=np.float64)
    if points.size == 0 and not names:
        points = points.reshape(0, 3)
    if points.ndim != 2 or points.shape[1] != 3:
        raise BadModelFile(f"{where}: keypoints must be (K, 3), one row of x, y, z per name; got shape "
                           f"{tuple(points.shape)}")
    if len(names) != len(points):
        raise BadModelFile(f"{where}: {len(names)} keypoint names for {len(points)} keypoints")
    keep_names, keep = [], []
    seen = set()
    for n, p in zip(names, points):
        if n in seen:
            warnings.warn(f"{where}: keypoint {n!r} repeated; keeping the first", stacklevel=3)
            continue
        if not np.isfinite(p).all():
            warnings.warn(f"{where}: keypoint {n!r} has non-finite coordinates; dropped", stacklevel=3)
            continue
        seen.add(n)
        keep_names.append(n)
        keep.append(p)
    arr = np.asarray(keep, dtype=np.float32).reshape(-1, 3)
    return keep_names, arr


def _model_from(path: Path, category: str | None, vertices, faces, names: list[str], points) -> Model:
    """The :class:`Model` read from ``path`` (named by its stem, ``category`` default from the stem); a failed
    check raises :class:`BadModelFile` naming ``path``."""
    try:
        category = category or category_from_stem(path.stem)
        return Model(name=path.stem, category=category, vertices=vertices, faces=faces, keypoint_names=names,
                     keypoints=points, source=path.name)
    except (TypeError, ValueError) as e:  # Model's checks name the model (the stem): name the file instead
        raise BadModelFile(f"{path}: {_reason(e).removeprefix(path.stem + ': ')}") from None


#: The arrays of a PASCAL3D+ ``.npz``.
_NPZ_ARRAYS = ("vertices", "faces", "keypoint_names", "keypoints")


def _npz_arrays(path: Path) -> dict[str, np.ndarray]:
    """The arrays :data:`_NPZ_ARRAYS` of an ``.npz`` (never unpickled); :class:`BadModelFile` when it is no
    readable archive holding them."""
    with open(path, "rb") as f:  # numpy leaves a file it opened itself open when it is no archive
        try:
            data = np.load(f, allow_pickle=False)
        except Exception as e:  # noqa: BLE001 - zipfile, numpy and OS errors of a file that is not an .npz
            raise BadModelFile(f"{path}: not a readable .npz archive ({_reason(e)})") from None
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise BadModelFile(f"{path}: a single array (.npy), not an .npz archive of {', '.join(_NPZ_ARRAYS)}")
        with data:
            missing = [k for k in _NPZ_ARRAYS if k not in data.files]
            if missing:
                raise BadModelFile(f"{path}: missing array(s) {missing} (a model needs {', '.join(_NPZ_ARRAYS)})")
            arrays = {}
            for k in _NPZ_ARRAYS:
                try:
                    arrays[k] = data[k]
                except Exception as e:  # noqa: BLE001 - an object array (pickled), a damaged member
                    raise BadModelFile(f"{path}: array {k!r} cannot be read ({_reason(e)})") from None
    return arrays


def load_cad_npz(path: str | Path) -> Model:
    """Read a PASCAL3D+ CAD ``.npz`` (``vertices``, ``faces``, ``keypoint_names``, ``keypoints``).

    CPU-side. The class is the file stem without digits. Nothing is unpickled.

    Returns:
        :class:`Model` with ``vertices (V,3) float32``, ``faces (F,3) long``, keypoints as stored
        (non-finite or repeated ones dropped with a warning), ``source`` = the file name.

    Raises:
        BadModelFile: not a readable ``.npz``, or an array missing or malformed (``keypoints`` must be
            ``(K, 3)`` for ``K`` names); the message names the file.
    """
    path = Path(path)
    a = _npz_arrays(path)
    try:
        vertices = np.asarray(a["vertices"], dtype=np.float32)
        if a["keypoint_names"].ndim != 1:
            raise ValueError(f"keypoint_names must be a list (K,), got shape {a['keypoint_names'].shape}")
        names = [str(n) for n in a["keypoint_names"]]
        points = np.asarray(a["keypoints"], dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise BadModelFile(f"{path}: {_reason(e)}") from None
    names, points = _clean_keypoints(names, points, str(path))
    return _model_from(path, None, vertices, a["faces"], names, points)


def _read_json_first_kept(path: Path):
    """A JSON file (:func:`~carvi_torch.io.outputs.read_json`); a key given twice in one object keeps its first
    value, with a warning naming the file. :class:`BadModelFile` naming the file when it is no JSON."""
    repeated: list[str] = []

    def first_kept(pairs: list) -> dict:
        obj: dict = {}
        for k, v in pairs:
            if k in obj:
                repeated.append(k)
            else:
                obj[k] = v
        return obj

    try:
        data = read_json(path, object_pairs_hook=first_kept)
    except ValueError as e:  # malformed, nested too deeply or not UTF-8 (the message names the file)
        raise BadModelFile(str(e)) from None
    for k in dict.fromkeys(repeated):
        warnings.warn(f"{path}: key {k!r} given more than once; keeping the first", stacklevel=4)
    return data


def _coordinate(c) -> float | None:
    """A JSON number as a float (beyond float range: infinite); ``None`` for anything else (text, booleans)."""
    if isinstance(c, bool) or not isinstance(c, (int, float)):
        return None
    try:
        return float(c)
    except OverflowError:  # an integer beyond float range
        return float("inf") if c > 0 else float("-inf")


def _read_keypoint_json(jpath: Path) -> tuple[str | None, list[str], np.ndarray]:
    """The class (``None``: not given) and keypoint names and ``(K, 3)`` points of a model's ``.json``
    (:class:`BadModelFile` naming it when malformed; null keypoints are absent)."""
    meta = _read_json_first_kept(jpath)
    if not isinstance(meta, dict):
        raise BadModelFile(f"{jpath}: expected a JSON object with 'class' and 'keypoints', got a "
                           f"{type(meta).__name__.replace('dict', 'object')}")
    cls = meta.get("class")
    if cls is not None and not isinstance(cls, str):
        raise BadModelFile(f"{jpath}: 'class' must be a class name (text), got {json.dumps(cls)[:60]}")
    kps = meta.get("keypoints")
    kps = {} if kps is None else kps
    if not isinstance(kps, dict):
        raise BadModelFile(f"{jpath}: 'keypoints' must be an object {{name: [x, y, z], ...}}, got "
                           f"{json.dumps(kps)[:60]}")
    names, points = [], []
    for n, p in kps.items():
        if p is None:
            continue
        xyz = [_coordinate(c) for c in p] if isinstance(p, list) else []
        if len(xyz) != 3 or None in xyz:
            raise BadModelFile(f"{jpath}: keypoint {n!r} is not three numbers [x, y, z]: {json.dumps(p)[:60]}")
        names.append(str(n))
        points.append(xyz)
    names, pts = _clean_keypoints(names, np.asarray(points, dtype=np.float64).reshape(-1, 3), str(jpath))
    return (cls.strip() or None) if cls is not None else None, names, pts


def _read_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``vertices (V, 3) float32`` and ``faces (F, 3) int64`` of a trimesh-readable file (a scene concatenated
    into one mesh; nothing merged); :class:`BadModelFile` naming the file when no reader understands it."""
    import trimesh

    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
        with np.errstate(over="ignore"):  # beyond float32: infinite, refused by Model's check
            vertices = np.asarray(mesh.vertices, dtype=np.float32).reshape(-1, 3)
        faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    except Exception as e:  # noqa: BLE001 - trimesh's readers raise many kinds on a file that is not what its name says
        raise BadModelFile(f"{path}: not a readable {path.suffix.lower()} mesh ({_reason(e)})") from None
    return vertices, faces


def load_mesh_with_keypoints(path: str | Path, keypoints_json: str | Path | None = None) -> Model:
    """Read a trimesh-readable mesh and its keypoint file ``<stem>.json`` (CPU-side).

    The JSON is ``{"class": "car", "keypoints": {"name": [x, y, z], ...}}``; ``class``
    defaults to the stem without digits; a keypoint given as ``null`` is absent; a key given
    twice keeps its first value (with a warning).

    Args:
        path: ``.ply``, ``.obj``, ``.off``, ``.stl``, ``.glb`` or ``.gltf`` file.
        keypoints_json: the keypoint file; default ``path`` with suffix ``.json``.

    Returns:
        :class:`Model` (a scene is concatenated into one mesh; vertices are not merged).

    Raises:
        FileNotFoundError: the mesh or its JSON is missing.
        BadModelFile: the JSON is malformed, the mesh unreadable or its vertices not finite (naming the file).
    """
    path = Path(path)
    jpath = Path(keypoints_json) if keypoints_json is not None else path.with_suffix(".json")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    if not jpath.is_file():
        raise FileNotFoundError(f"{path}: keypoint file {jpath.name} not found beside it "
                                '(expected {"class": ..., "keypoints": {"name": [x, y, z], ...}})')
    category, names, pts = _read_keypoint_json(jpath)
    vertices, faces = _read_mesh(path)
    return _model_from(path, category, vertices, faces, names, pts)


def _check_renderable(model: Model, path: Path) -> None:
    """:class:`BadModelFile` naming ``path`` when renders of ``model`` would be empty or meaningless: no faces, no
    extent (sizes relative to the mesh, any unit), no keypoints, or keypoints far outside the mesh
    (:data:`KEYPOINT_OFF_MESH_MAX`)."""
    if model.faces.shape[0] == 0:
        raise BadModelFile(f"{path}: no faces (an empty or unreadable file, or points only): nothing to render")
    tri = model.vertices.double()[model.faces]  # (F, 3, 3)
    lo, hi = tri.reshape(-1, 3).amin(0), tri.reshape(-1, 3).amax(0)
    diag = float((hi - lo).norm())
    if not diag > 1e-6 * float(tri.abs().max()):  # below float32's resolution of its coordinates, or zero
        raise BadModelFile(f"{path}: every vertex of its faces lies at one point (no extent): nothing to render")
    area = float(torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1).norm(dim=1).sum())
    if not area > 1e-9 * diag**2:
        raise BadModelFile(f"{path}: every triangle is flat (no area): nothing to render")
    if model.keypoints.shape[0] == 0:
        raise BadModelFile(f"{path}: no keypoints (every render annotates keypoints)")
    kp = model.keypoints.double()
    off = (kp - torch.maximum(torch.minimum(kp, hi), lo)).norm(dim=1)  # distance from the mesh's bounding box
    far = [n for n, d in zip(model.keypoint_names, off.tolist()) if d > KEYPOINT_OFF_MESH_MAX * diag]
    if far:
        raise BadModelFile(f"{path}: keypoint(s) {shown_names(far, quoted=True)} lie far outside the mesh (up to "
                           f"{float(off.max()) / diag:.3g} times its size away; in other units than the mesh?)")


def load_model(path: str | Path) -> Model:
    """Read one model: ``.npz`` through :func:`load_cad_npz`, else :func:`load_mesh_with_keypoints`; and check
    that renders can use it (faces with an extent, keypoints on or near the mesh).

    Raises:
        FileNotFoundError: the file, or a mesh's keypoint file, is missing.
        BadModelFile: anything else wrong with it, in one line naming the file (see the module's docstring).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".npz", *MESH_SUFFIXES):
        raise BadModelFile(f"{path}: unsupported model file (expected .npz or one of {', '.join(MESH_SUFFIXES)})")
    try:
        model = load_cad_npz(path) if suffix == ".npz" else load_mesh_with_keypoints(path)
    except BadModelFile:
        raise
    except (TypeError, ValueError) as e:  # any other check: name the file
        raise BadModelFile(f"{path}: {_reason(e)}") from None
    _check_renderable(model, path)
    return model


def _skip_line(e: Exception, path: Path) -> str:
    """Why the model file ``path`` is skipped, in one line naming it (``e`` from :func:`load_model`)."""
    if isinstance(e, OSError) and e.strerror:  # the system's error reading it
        return f"{path}: {e.strerror}; skipped"
    return f"{e}; skipped"


def _distinct_names(models: list[Model], directory: Path) -> list[Model]:
    """``models`` less those whose name (file stem) another one shares, each such name with a warning."""
    names = [m.name for m in models]
    for dup in sorted({n for n in names if names.count(n) > 1}):
        files = ", ".join(m.source for m in models if m.name == dup)
        warnings.warn(f"{directory}: files {files} share the model name {dup!r} (and its keypoint file); "
                      "skipped: rename all but one", stacklevel=3)
    return [m for m in models if names.count(m.name) == 1]


def load_models(directory: str | Path, sides: Literal["class", "as-given"] = "class", strict: bool = False
                ) -> list[Model]:
    """Every model of a directory (not recursive), sorted by file name (deterministic).

    Reads ``*.npz`` (PASCAL3D+ form) and meshes with a ``.json`` keypoint file beside
    them. A file that cannot be used is skipped with a warning, one line naming it, and the
    rest are read: a mesh without a ``.json`` (it has no keypoints to annotate), any
    :class:`BadModelFile` of :func:`load_model`, a file the system cannot read, and files
    sharing one model name (file stem).
    With ``sides="class"`` (the default) a left/right pair that one model names from the other
    side than the rest of its class is renamed (:func:`harmonize_sides`, with a warning);
    ``"as-given"`` keeps every name as stored. With ``strict`` the first file that would be skipped raises
    instead (a benchmark on a fixed set of models must not run on fewer).

    Raises:
        FileNotFoundError: ``directory`` does not exist.
        ValueError: no usable model found; with ``strict``, any file skipped (its reason).
    """
    if sides not in ("class", "as-given"):
        raise ValueError(f"sides must be 'class' or 'as-given', got {sides!r}")
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such directory of models")
    models: list[Model] = []
    skipped = 0
    for path in sorted(directory.iterdir(), key=lambda p: p.name):
        suffix = path.suffix.lower()
        if not path.is_file() or path.name.startswith(".") or suffix not in (".npz", *MESH_SUFFIXES):
            continue
        why = None
        if suffix != ".npz" and not path.with_suffix(".json").is_file():
            why = f"{path}: no {path.stem}.json with its class and keypoints beside it; skipped"
        else:
            try:
                models.append(load_model(path))
            except (BadModelFile, OSError) as e:  # one bad model: its reason, and the rest goes on
                why = _skip_line(e, path)
        if why is not None:
            if strict:
                raise ValueError(why)
            warnings.warn(why, stacklevel=2)
            skipped += 1
    distinct = _distinct_names(models, directory)
    if strict and len(distinct) < len(models):
        raise ValueError(f"{directory}: files share a model name (their stems)")
    skipped += len(models) - len(distinct)
    models = distinct
    if not models:
        raise ValueError(f"{directory}: no usable models (each skipped above)" if skipped else
                         f"{directory}: no models (.npz, or {'/'.join(MESH_SUFFIXES)} with a .json beside)")
    return harmonize_sides(models) if sides == "class" else models
