"""The shape error of every object of an evaluation (:func:`carvi_torch.evaluate.evaluate`'s scoring).

* :func:`gt_problem`, :func:`camera_problem`: what makes a ``gt.json`` record or a run's camera unusable (the
  object is then left out with that reason, and the rest evaluated);
* :class:`Reason`: why an object has no shape error or no refined camera, with its kind (:data:`ReasonKind`),
  which the objects are grouped and counted under;
* :func:`posed_gt_mesh`: an annotation's ground-truth mesh in its reference camera frame;
* :func:`load_recon_mesh`: a run's mesh of an object (:func:`read_mesh`: a file that holds no usable mesh, one
  that cannot be read, has no face, non-finite vertices or a face index outside them, is a ``ValueError`` naming
  it; the ground-truth meshes are read the same way);
* :class:`ShapeScorer`: one object's error for every method (and the baselines) against its posed ground truth,
  or why there is none;
* :func:`score_shapes`: every object's, in this process or in worker processes (:func:`default_jobs`), one
  torch thread each: the errors do not depend on how many.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import multiprocessing as mp
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import trimesh
from tqdm.auto import tqdm

from ..cameras import ScaledOrthographic
from ..io.layout import object_mesh
from ..mesh import read_mesh_arrays
from ..io.results import ROTATION_TOLERANCE, camera_record_problem, numbers, rotation_problem, shown
from ..runtime import LeanProcessPool, cores, start_method, torch_threads
from . import metrics

__all__ = ["POOL_FROM", "MAX_JOBS", "ROTATION_TOLERANCE", "NO_RECONSTRUCTION", "ReasonKind", "Reason",
           "default_jobs", "numbers", "rotation_problem", "gt_problem", "camera_problem", "read_mesh", "posed_gt_mesh",
           "load_recon_mesh", "ShapeScorer", "score_shapes", "score_mesh", "puffball_mesh", "sfmc_mesh"]

log = logging.getLogger(__name__)

#: Objects from which :func:`default_jobs` scores the shapes in worker processes (starting them, a second or two
#: each, costs more than it saves on fewer).
POOL_FROM = 16
#: At most this many worker processes by default (each holds torch and its ground-truth meshes: a few hundred MB).
MAX_JOBS = 8
#: The reason of an object that a method has no mesh for (and nothing more is known).
NO_RECONSTRUCTION = "no reconstruction"

#: The kinds of :class:`Reason`: what the objects left out are grouped and counted under (``missing_reasons``, the
#: notes). Why a method has no shape error for an object: no mesh (:data:`NO_RECONSTRUCTION`), an unfinished run's
#: object not reconstructed yet, one the run skipped, an unusable ``cameras.json`` of its class, a mesh file that
#: cannot be read, a mesh the metric cannot score, a baseline's missing input (``no mask``, ``no SfM camera``),
#: or not scored at all (``--viewpoints-only``). Why an object has no usable refined camera: not in
#: ``cameras.json``, none there, a non-finite one, an unusable file, or an unusable entry or camera (these three
#: also say what of a ``cameras.json`` was unusable: ``camera_problems``).
ReasonKind = Literal["no reconstruction", "not reconstructed yet", "skipped by the run", "unusable cameras.json",
                     "unreadable mesh", "unscorable mesh", "no mask", "no SfM camera", "not scored",
                     "not in cameras.json", "no refined camera", "non-finite refined camera",
                     "cameras.json entry not an object", "unusable sfm camera in cameras.json",
                     "unusable refined camera in cameras.json"]


@dataclasses.dataclass(frozen=True)
class Reason:
    """Why an object is left out of a score: its ``kind``, which such objects are grouped and counted under, and the
    ``text`` that says it for this object (naming its file, the run's reason or what the metric found, where there
    is more to say than the kind).

    Example:
        >>> Reason.of("unreadable mesh", "cannot read 3.ply: no such file")
        Reason(kind='unreadable mesh', text='unreadable mesh: cannot read 3.ply: no such file')
        >>> Reason.of(NO_RECONSTRUCTION).entry()
        {'error_percent': None, 'reason': 'no reconstruction', 'kind': 'no reconstruction'}
    """

    kind: ReasonKind
    text: str

    @classmethod
    def of(cls, kind: ReasonKind, detail: str | None = None) -> Reason:
        """The reason of ``kind`` whose text is the kind, followed by ``": "`` and ``detail`` where there is one."""
        return cls(kind, kind if detail is None else f"{kind}: {detail}")

    def entry(self, **fields) -> dict:
        """A method's entry in an object's row without a shape error: ``error_percent`` ``None``, ``fields``, and
        the ``reason`` (its text) with its ``kind``."""
        return {"error_percent": None, **fields, "reason": self.text, "kind": self.kind}


def gt_problem(entry) -> str | None:
    """What makes an annotation's ``gt.json`` record unusable (an object with ``mesh``, a file name; ``R`` a
    rotation, :func:`rotation_problem`; ``s`` a finite positive number; ``t`` two finite numbers), ``None`` when
    nothing does. The mesh file itself is read when the object is scored (:func:`posed_gt_mesh`).

    Example:
        >>> gt_problem({"mesh": "m.ply", "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": 2.0, "t": [0, 1]}) is None
        True
        >>> gt_problem({"mesh": "m.ply", "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": None, "t": [0, 1]})
        's is None, not a finite positive number'
        >>> gt_problem("oops")
        "its entry is 'oops', not an object"
    """
    if not isinstance(entry, dict):
        return f"its entry is {shown(entry)}, not an object"
    mesh = entry.get("mesh")
    if not isinstance(mesh, str) or not mesh:
        return f"mesh is {shown(mesh)}, not a file name"
    return camera_record_problem(entry)


def camera_problem(cam) -> str | None:
    """What makes a camera of a run's ``cameras.json`` (an entry's ``sfm`` or ``refined``) unusable, ``None`` when
    nothing does (:func:`~carvi_torch.io.results.camera_record_problem` with ``finite=False``: a non-finite
    camera, an estimate that failed, is usable; the viewpoint report leaves it out).

    Example:
        >>> camera_problem({"R": [[1, 0, 0], [0, 1, 0]], "s": 1.0, "t": [0, 0]})
        'R is not 3 x 3 numbers'
        >>> camera_problem({"R": [[float("nan")] * 3] * 3, "s": 1.0, "t": [0, 0]}) is None
        True
    """
    return camera_record_problem(cam, finite=False)


def read_mesh(path: Path) -> trimesh.Trimesh:
    """The mesh in the file ``path`` as written (:func:`~carvi_torch.mesh.read_mesh_arrays`); ``ValueError`` naming
    the file when there is none it can be read as (no file, a format trimesh does not read, a damaged file, no
    face, a face index outside the vertices, or a vertex a face names that is not finite)."""
    if not Path(path).is_file():
        raise ValueError(f"cannot read {path}: {'a folder, not a file' if Path(path).is_dir() else 'no such file'}")
    try:
        v, f = read_mesh_arrays(path, used_only=True)  # the metric reads only the vertices the faces name
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds for a file it cannot read
        lines = str(e).strip().splitlines()
        raise ValueError(f"cannot read {path}: {type(e).__name__}" + (f": {lines[0]}" if lines else "")) from None
    return trimesh.Trimesh(v, f, process=False)


def posed_gt_mesh(entry: dict, root: Path, cache: dict | None = None) -> tuple[trimesh.Trimesh, float]:
    """The ground-truth mesh of one annotation in its reference camera frame (image pixels).

    ``entry`` is the annotation's record of ``gt.json`` (``mesh`` path relative to ``root``, true
    ``R``, ``s``, ``t``): vertices ``X`` go to ``(u, v, depth) = (s R[:2] X + t, s R[2] X)``.

    Returns:
        the posed mesh and the normalising diagonal: ``s`` times the bounding-box diagonal of the
        model in its own frame (the paper's normalisation; a box taken in the camera frame would
        depend on the view).
    """
    path = (root / entry["mesh"]).resolve()
    if cache is not None and path in cache:
        base = cache[path]
    else:
        base = read_mesh(path)
        if cache is not None:
            cache[path] = base
    cam = ScaledOrthographic.from_list([entry], dtype=torch.float64)
    V = torch.from_numpy(np.asarray(base.vertices, dtype=np.float64))
    Vc = cam.to_camera_frame(V)[0].numpy()
    used = np.unique(np.asarray(base.faces))
    diag = float(cam.s[0]) * metrics.bounding_box_diagonal(V[used])
    return trimesh.Trimesh(Vc, np.asarray(base.faces), process=False), diag


def load_recon_mesh(recon: Path, cls: str, aid, cams: dict | None, mesh_format: str) -> trimesh.Trimesh | None:
    """The run's mesh of object ``aid``, or ``None``: no mesh, or the object is not in the class's
    ``cameras.json`` (``cams``, its content), which holds the objects of the run's latest input (a mesh an
    earlier run left for an object the input has since dropped is not the run's; a folder of meshes without
    ``cameras.json`` (``cams`` ``None``), another method's, is taken as it is). The file is the one the export
    takes (:func:`~carvi_torch.io.layout.object_mesh`): in the run's ``mesh_format`` where there is one, so a
    mesh of another format left beside it (from before a change of ``mesh_format``) is not scored. A file it
    cannot read is a ``ValueError`` naming it (:func:`read_mesh`)."""
    if cams is not None and str(aid) not in cams.get("cameras", {}):
        return None
    path = object_mesh(recon / cls, aid, mesh_format)
    return None if path is None else read_mesh(path)


@dataclasses.dataclass
class ShapeScorer:
    """The shape errors of one object: every method's mesh (and the baselines') against its posed ground truth."""

    gt_root: Path  # the folder the meshes of gt.json are relative to
    recons: dict  # method -> reconstruction folder
    cameras: dict  # method -> class -> cameras.json content (None: none)
    mesh_formats: dict  # method -> its run's mesh_format (config.yaml's mesh.format; the default without one)
    step_percent: float
    baselines: bool
    collections: dict  # class -> its loaded collection (the baselines' masks)
    mesh_cache: dict = dataclasses.field(default_factory=dict)
    rows_of: dict = dataclasses.field(default_factory=dict)  # class -> annotation id (str) -> its collection row
    #: method -> why an object has no mesh (a :class:`Reason`): keyed ``(class, annotation id as str)``, then
    #: ``(class, None)`` for every object of the class, then ``(None, None)`` for every object
    #: (:meth:`missing_reason`)
    missing: dict = dataclasses.field(default_factory=dict)

    def missing_reason(self, name: str, cls: str, aid) -> Reason:
        """Why method ``name`` has no mesh of object ``aid``: the most specific reason :attr:`missing` knows,
        else :data:`NO_RECONSTRUCTION`.

        Example:
            >>> late = Reason("not reconstructed yet", "not reconstructed yet (the run is unfinished)")
            >>> s = ShapeScorer(Path("."), {}, {}, {}, 1.0, False, {}, missing={"B": {(None, None): late}})
            >>> s.missing_reason("B", "car", 3).kind, s.missing_reason("A", "car", 3).kind
            ('not reconstructed yet', 'no reconstruction')
        """
        why = self.missing.get(name, {})
        return (why.get((cls, str(aid))) or why.get((cls, None)) or why.get((None, None))
                or Reason.of(NO_RECONSTRUCTION))

    def _row(self, cls: str, aid) -> int | None:
        """The row of ``aid`` in its class's collection (``None``: not there), the class's index built once."""
        coll = self.collections.get(cls)
        if coll is None:
            return None
        if cls not in self.rows_of:
            self.rows_of[cls] = {str(a): i for i, a in enumerate(coll.annotation_ids)}
        return self.rows_of[cls].get(str(aid))

    def score(self, aid: str, entry: dict, row: dict) -> None:
        """Add each method's error (or why there is none) to ``row``, or a ``reason`` when the ground truth fails."""
        cls = row["class"]
        try:
            posed, diag = posed_gt_mesh(entry, self.gt_root, self.mesh_cache)
            gt_mesh = metrics.EvaluationMesh(posed, name="gt")
            gt_mesh.require_valid()
            gt_mesh = gt_mesh.with_diag(diag)
        except (ValueError, FileNotFoundError, KeyError) as e:
            row["reason"] = f"ground truth unusable: {e}"
            return
        step = self.step_percent / 100.0 * gt_mesh.diag
        for name, rdir in self.recons.items():
            try:
                m = load_recon_mesh(Path(rdir), cls, aid, self.cameras[name][cls], self.mesh_formats[name])
            except ValueError as e:  # a file that is no mesh: this method's object, the others go on
                row[name] = Reason.of("unreadable mesh", str(e)).entry()
                continue
            row[name] = score_mesh(m, gt_mesh, step, self.missing_reason(name, cls, aid))
        if self.baselines:
            row["Puffball"] = score_mesh(puffball_mesh(self.collections.get(cls), self._row(cls, aid)), gt_mesh,
                                         step, Reason.of("no mask"))
            first = next(iter(self.recons))
            row["SFMc"] = score_mesh(sfmc_mesh(self.cameras[first][cls], aid), gt_mesh, step,
                                    Reason.of("no SfM camera"))


def default_jobs(n_objects: int) -> int:
    """Processes that score ``n_objects`` objects' shapes: one per core, at most :data:`MAX_JOBS`; 1 (this
    process) below :data:`POOL_FROM` objects or on one core.

    One torch thread per process: the scoring is many small tensor operations, which two threads share at a
    gain of about 1.2x on an idle host, while threads that wait for one another slow down by an order of
    magnitude once the host is busy (``carvi_torch.evaluate``'s docstring, *Cost*).

    Example:
        >>> default_jobs(3)
        1
    """
    return 1 if n_objects < POOL_FROM else max(1, min(cores(), MAX_JOBS))


#: The scorer of a worker process (:func:`_init_scorer`).
_WORKER_SCORER: ShapeScorer | None = None


def _init_scorer(scorer: ShapeScorer) -> None:
    global _WORKER_SCORER
    torch.set_num_threads(1)
    _WORKER_SCORER = scorer


def _score_in_worker(job: tuple) -> dict:
    aid, entry, row = job
    _WORKER_SCORER.score(aid, entry, row)
    return row


def score_shapes(scorer: ShapeScorer, work: list, jobs: int, progress: bool) -> list[dict]:
    """Every ``(aid, entry, row)`` of ``work`` scored (:meth:`ShapeScorer.score`), its rows in order: in ``jobs``
    worker processes, or in this one with one torch thread (``jobs`` 1, or when the processes cannot start)."""
    if jobs > 1 and len(work) > 1:
        pool = None
        try:
            pool = LeanProcessPool(min(jobs, len(work)), mp_context=mp.get_context(start_method()),
                                   initializer=_init_scorer, initargs=(scorer,))
            chunk = max(1, min(16, len(work) // (4 * jobs)))
            rows = list(tqdm(pool.map(_score_in_worker, work, chunksize=chunk), total=len(work), desc="evaluate",
                             disable=not progress))
            pool.shutdown()
            return rows
        except (OSError, BrokenProcessPool) as e:
            log.warning(f"evaluate: worker processes failed ({type(e).__name__}: {e}); scoring here")
            if pool is not None:
                pool.stop()
        except BaseException:
            if pool is not None:
                pool.stop()
            raise
    with torch_threads(1):
        for aid, entry, row in tqdm(work, desc="evaluate", disable=not progress):
            scorer.score(aid, entry, row)
    return [row for _aid, _entry, row in work]


def score_mesh(mesh, gt_mesh, step, missing_reason: Reason) -> dict:
    """``{"error_percent", "offset", "reason": None}`` of one mesh against its posed ground truth; without an error,
    :meth:`Reason.entry`'s: ``missing_reason`` without a mesh, or an ``unscorable mesh`` with the metric's reason
    when it cannot score it."""
    if mesh is None:
        return missing_reason.entry()
    try:
        r = metrics.evaluate_reconstruction(mesh, gt_mesh, step=step)
    except ValueError as e:
        return Reason("unscorable mesh", str(e)).entry()
    err = r["error_percent"]
    if not math.isfinite(err):
        return Reason("unscorable mesh", r.get("reason") or "no finite error").entry(offset=r.get("offset"))
    return {"error_percent": float(err), "offset": r.get("offset"), "reason": None}


def puffball_mesh(coll, i: int | None):
    """Puffball of row ``i``'s canvas mask in the collection ``coll``, mapped to image pixels (``None`` without a
    collection, a row or a mask)."""
    if coll is None or i is None:
        return None
    from .baselines import puffball

    m = puffball(coll.masks[i])
    if m is None or len(m.faces) == 0:
        return None
    a = float(coll.canvas_from_image.scale[i])
    b = coll.canvas_from_image.offset[i].double().numpy()
    V = np.asarray(m.vertices, dtype=np.float64).copy()
    V[:, :2] = (V[:, :2] - b) / a
    V[:, 2] = V[:, 2] / a
    return trimesh.Trimesh(V, np.asarray(m.faces), process=False)


def sfmc_mesh(cj: dict | None, aid: int):
    """Convex hull of the SfM mean shape seen by the annotation's refined camera (image pixels); ``cj``: the
    class's ``cameras.json`` (``None``: none)."""
    if cj is None:
        return None
    cam = cj.get("cameras", {}).get(str(aid), {}).get("refined")
    shape = cj.get("mean_shape")
    if cam is None or camera_problem(cam) or not isinstance(shape, dict):
        return None
    S = torch.tensor([v for v in shape.values() if numbers(v, (3,))], dtype=torch.float64)
    if len(S) < 4:
        return None
    from .baselines import sfm_convex_hull

    return sfm_convex_hull(S, ScaledOrthographic.from_list([cam], dtype=torch.float64))
