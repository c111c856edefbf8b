"""What a writer process runs: mesh one object and write its files. Imports no torch (a fast start).

A writer process watches the run that started it: when the run is gone (killed, even with
SIGKILL), the writer exits within a second, and the forkserver that forked it follows, so a killed
run leaves nothing running. It ignores Ctrl-C (SIGINT, which a terminal sends to the whole process
group): the run handles it and stops its writers, which would otherwise each print a traceback.

Example:
    >>> import numpy as np, tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> occ = np.zeros((4, 4, 4), bool); occ[1:3, 1:3, 1:3] = True
    >>> job = dict(occupancy=occ, voxel_to_image=np.eye(4), voxel_to_canvas=np.eye(4), canvas_scale=1.0,
    ...            canvas_offset=np.zeros(2, np.float32), surrogates=np.zeros(0, np.int64), largest_component=False,
    ...            proposals=None, scores=None, voxel_path=str(d / "v.npz"), mesh_path=str(d / "m.ply"))
    >>> write_object(job)["ok"], (d / "m.ply").is_file()
    (True, True)
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from .. import mesh
from ..quality import reconstruction_iou
from ..runtime import ignore_interrupt, peak_rss_mb, watch_parent
from .layout import MESH_MEMBER, SETTINGS_MEMBER, mesh_record
from .outputs import write_json, write_npz

__all__ = ["write_object", "write_object_safe", "start_worker", "watch_parent", "init_worker"]


def write_object(job: dict) -> dict:
    """Mesh and files of one reconstructed object (in a writer process, or inline).

    Takes host (numpy) data only; a job with ``mesh_vertices`` and ``mesh_faces`` was meshed by the
    run (its occupancy is final: ``largest_component`` is not applied again). Writes the proposals
    (studies) and scores first, then the mesh, then the voxels with the object's ``input_fingerprint`` and the
    ``settings`` it is made with (:data:`~carvi_torch.io.layout.SETTINGS_MEMBER`; the job's, when it has them): an
    object counts as finished once its voxels file exists and holds the fingerprint of its current inputs
    (:func:`~carvi_torch.io.layout.finished`). The voxels and mesh files are moved into place whole but not flushed
    to the disk (``sync=False``): a machine crash may leave one damaged, which a resumed run finds (every member
    of the voxels file read, the mesh's faces checked against the count the voxels file records) and redoes. The
    studies' proposals and scores, which no check reads, are flushed. Returns ``ok``, ``reason``, ``mesh_seconds``,
    ``write_seconds`` and ``reconstruction_iou`` (the value written into the voxels file, ``None`` without a
    ``mask``), which the run's ``cameras.json`` takes without opening the file again.
    """
    t0 = time.perf_counter()
    occ = job["occupancy"]
    v2img = job["voxel_to_image"]
    if job.get("mesh_faces") is not None:  # meshed already, in the run's process (mesh.mesher=torch)
        m = mesh.trimesh_mesh(job["mesh_vertices"], job["mesh_faces"])
    else:
        if job["largest_component"]:
            occ = mesh.largest_component(occ)
        m = mesh.occupancy_to_mesh(occ, v2img)
    t1 = time.perf_counter()
    if len(m.faces) == 0:
        return dict(ok=False, reason="selected proposal has no surface", mesh_seconds=t1 - t0, write_seconds=0.0)
    if job.get("proposals") is not None:
        write_npz(job["proposals_path"], **job["proposals"])  # flushed: finished() does not check it
    if job.get("scores") is not None:
        write_json(job["scores_path"], job["scores"], indent=None)  # flushed: finished() does not check it
    extra = {}
    if job.get("mask") is not None:  # the quality signal of the reconstruction (carvi_torch.quality)
        extra["reconstruction_iou"] = np.float64(reconstruction_iou(occ, job["voxel_to_canvas"], job["mask"]))
    if job.get("input_fingerprint"):  # what the object was made from (a rerun resumes it only if unchanged)
        extra["input_fingerprint"] = np.asarray(job["input_fingerprint"], dtype=str)
    if job.get("settings"):  # the settings it was made with (JSON text: layout.settings_text)
        extra[SETTINGS_MEMBER] = np.asarray(job["settings"], dtype=str)
    extra[MESH_MEMBER] = mesh_record(Path(job["mesh_path"]).suffix[1:].lower(), len(m.faces))
    mesh.write_mesh(m, job["mesh_path"], sync=False)
    # the voxels file last: it holds the fingerprint, so a stop between the two files leaves an earlier run's
    # voxels (another fingerprint, or none) beside the new mesh, and the object is redone
    write_npz(job["voxel_path"], sync=False, occupancy=occ, voxel_to_camera=v2img,
              voxel_to_canvas=job["voxel_to_canvas"],
              voxel_to_object=job.get("voxel_to_object", np.full((4, 4), np.nan)), canvas_scale=job["canvas_scale"],
              canvas_offset=job["canvas_offset"], surrogates=job["surrogates"], **extra)
    return dict(ok=True, reason=None, mesh_seconds=t1 - t0, write_seconds=time.perf_counter() - t1,
                reconstruction_iou=float(extra["reconstruction_iou"]) if "reconstruction_iou" in extra else None)


def write_object_safe(job: dict) -> dict:
    """:func:`write_object`, with any error of this object booked as its own failure (reason)
    instead of surfacing later, at some other object's turn (or in another class); plus the
    process's peak memory (``peak_rss_mb``, ``None`` where unknown)."""
    try:
        out = write_object(job)
    except Exception as e:  # noqa: BLE001 - reported per object, the run goes on
        out = dict(ok=False, reason=f"writing failed: {type(e).__name__}: {e}", mesh_seconds=0.0, write_seconds=0.0)
    out["peak_rss_mb"] = peak_rss_mb()
    return out


def start_worker() -> int:
    """No-op run by each writer process once, so that all of them start early; returns the pid."""
    return os.getpid()


def init_worker(run_pid: int) -> None:
    """Process initializer of a writer: ignore Ctrl-C (the run stops its writers) and
    :func:`watch_parent` ``run_pid``."""
    ignore_interrupt()
    watch_parent(run_pid)
