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
the file: non-finite keypoints and repeated keypoint names (the first is kept).

Left and right are not always named alike across a class's models: PASCAL3D+'s motorbike01
names its handlebar ends from the other side than the other three motorbikes. A human
annotator of its photographs would name them like the others, so :func:`load_models`
exchanges such a pair's names (:func:`harmonize_sides`, with a warning naming the model);
``sides="as-given"`` keeps the names as stored.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, Sequence

import numpy as np
import torch

from ..collection import infer_flip_pairs  # re-exported: name-based left/right pairs

__all__ = ["Model", "MESH_SUFFIXES", "SIDE_VOTE_MIN", "side_disagreements", "turned_models", "harmonize_sides",
           "side_swaps_of",
           "load_cad_npz", "load_mesh_with_keypoints", "load_model", "load_models",
           "infer_flip_pairs", "category_from_stem"]

#: File suffixes read through trimesh (a ``.json`` with the keypoints must sit beside the mesh).
MESH_SUFFIXES = (".ply", ".obj", ".off", ".stl", ".glb", ".gltf")


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
        self.faces = torch.as_tensor(self.faces, dtype=torch.long)
        self.keypoints = torch.as_tensor(self.keypoints, dtype=torch.float32).reshape(-1, 3)
        self.keypoint_names = [str(n) for n in self.keypoint_names]
        if self.vertices.dim() != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"{self.name}: vertices must be (V, 3), got {tuple(self.vertices.shape)}")
        if self.faces.dim() != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"{self.name}: faces must be (F, 3), got {tuple(self.faces.shape)}")
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


def _clean_keypoints(names: Sequence[str], points: np.ndarray, where: str) -> tuple[list[str], np.ndarray]:
    """Drop non-finite and repeated keypoints (with a warning naming ``where``)."""
    names = [str(n) for n in names]
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(names) != len(points):
        raise ValueError(f"{where}: {len(names)} keypoint names for {len(points)} keypoints")
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


def load_cad_npz(path: str | Path) -> Model:
    """Read a PASCAL3D+ CAD ``.npz`` (``vertices``, ``faces``, ``keypoint_names``, ``keypoints``).

    CPU-side. The class is the file stem without digits.

    Returns:
        :class:`Model` with ``vertices (V,3) float32``, ``faces (F,3) long``, keypoints as stored
        (non-finite or repeated ones dropped with a warning), ``source`` = the file name.

    Raises:
        ValueError: a required array is missing or malformed.
    """
    path = Path(path)
    with np.load(path, allow_pickle=False) as data:
        missing = [k for k in ("vertices", "faces") if k not in data]
        if missing:
            raise ValueError(f"{path}: missing array(s) {missing}")
        vertices = np.asarray(data["vertices"], dtype=np.float32)
        faces = np.asarray(data["faces"], dtype=np.int64)
        names = [str(n) for n in data["keypoint_names"]] if "keypoint_names" in data else []
        points = np.asarray(data["keypoints"]) if "keypoints" in data else np.zeros((0, 3))
    names, points = _clean_keypoints(names, points, str(path))
    return Model(name=path.stem, category=category_from_stem(path.stem), vertices=torch.from_numpy(vertices),
                 faces=torch.from_numpy(faces), keypoint_names=names, keypoints=torch.from_numpy(points),
                 source=path.name)


def load_mesh_with_keypoints(path: str | Path, keypoints_json: str | Path | None = None) -> Model:
    """Read a trimesh-readable mesh and its keypoint file ``<stem>.json`` (CPU-side).

    The JSON is ``{"class": "car", "keypoints": {"name": [x, y, z], ...}}``; ``class``
    defaults to the stem without digits; a keypoint given as ``null`` is absent.

    Args:
        path: ``.ply``, ``.obj``, ``.off``, ``.stl``, ``.glb`` or ``.gltf`` file.
        keypoints_json: the keypoint file; default ``path`` with suffix ``.json``.

    Returns:
        :class:`Model` (a scene is concatenated into one mesh; vertices are not merged).

    Raises:
        FileNotFoundError: the mesh or its JSON is missing.
        ValueError: the JSON is malformed.
    """
    import trimesh

    from ..io.outputs import read_json

    path = Path(path)
    jpath = Path(keypoints_json) if keypoints_json is not None else path.with_suffix(".json")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such mesh file")
    if not jpath.is_file():
        raise FileNotFoundError(f"{path}: keypoint file {jpath.name} not found beside it "
                                '(expected {"class": ..., "keypoints": {"name": [x, y, z], ...}})')
    meta = read_json(jpath)
    if not isinstance(meta, dict):
        raise ValueError(f"{jpath}: expected a JSON object with 'class' and 'keypoints'")
    kps = meta.get("keypoints", {}) or {}
    if not isinstance(kps, dict):
        raise ValueError(f"{jpath}: 'keypoints' must be an object {{name: [x, y, z]}}")
    names, points = [], []
    for n, p in kps.items():
        if p is None:
            continue
        try:
            arr = np.asarray(p, dtype=np.float64).reshape(3)
        except (TypeError, ValueError):
            raise ValueError(f"{jpath}: keypoint {n!r} is not three numbers: {p!r}") from None
        names.append(str(n))
        points.append(arr)
    names, pts = _clean_keypoints(names, np.asarray(points).reshape(-1, 3), str(jpath))
    mesh = trimesh.load(str(path), force="mesh", process=False)
    vertices = np.asarray(mesh.vertices, dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    category = str(meta.get("class") or category_from_stem(path.stem))
    return Model(name=path.stem, category=category, vertices=torch.from_numpy(vertices),
                 faces=torch.from_numpy(faces), keypoint_names=names, keypoints=torch.from_numpy(pts),
                 source=path.name)


def load_model(path: str | Path) -> Model:
    """Read one model: ``.npz`` through :func:`load_cad_npz`, else :func:`load_mesh_with_keypoints`."""
    path = Path(path)
    if path.suffix.lower() == ".npz":
        return load_cad_npz(path)
    if path.suffix.lower() in MESH_SUFFIXES:
        return load_mesh_with_keypoints(path)
    raise ValueError(f"{path}: unsupported model file (expected .npz or one of {', '.join(MESH_SUFFIXES)})")


def load_models(directory: str | Path, sides: Literal["class", "as-given"] = "class") -> list[Model]:
    """Every model of a directory (not recursive), sorted by file name (deterministic).

    Reads ``*.npz`` (PASCAL3D+ form) and meshes with a ``.json`` keypoint file beside
    them; a mesh without one is skipped with a warning (it has no keypoints to annotate).
    With ``sides="class"`` (the default) a left/right pair that one model names from the other
    side than the rest of its class is renamed (:func:`harmonize_sides`, with a warning);
    ``"as-given"`` keeps every name as stored.

    Raises:
        FileNotFoundError: ``directory`` does not exist.
        ValueError: no model found, or two models share a name (file stem).
    """
    if sides not in ("class", "as-given"):
        raise ValueError(f"sides must be 'class' or 'as-given', got {sides!r}")
    directory = Path(directory)
    if not directory.is_dir():
        raise FileNotFoundError(f"{directory}: no such directory of models")
    models: list[Model] = []
    for path in sorted(directory.iterdir(), key=lambda p: p.name):
        suffix = path.suffix.lower()
        if not path.is_file() or path.name.startswith(".") or suffix not in (".npz", *MESH_SUFFIXES):
            continue
        if suffix != ".npz" and not path.with_suffix(".json").is_file():
            warnings.warn(f"{path}: no {path.stem}.json with its class and keypoints beside it; skipped",
                          stacklevel=2)
            continue
        models.append(load_model(path))
    if not models:
        raise ValueError(f"{directory}: no models (.npz, or {'/'.join(MESH_SUFFIXES)} with a .json beside)")
    names = [m.name for m in models]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"{directory}: several files share the model name(s) {dup}")
    return harmonize_sides(models) if sides == "class" else models
