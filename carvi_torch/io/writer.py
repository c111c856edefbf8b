"""Meshes and files of reconstructed objects, written by worker processes beside the device work.

Meshing (marching cubes) and writing an object take about 10-25 ms of CPU; in worker
processes they overlap the carving of the next objects. Workers are started with
``forkserver`` where the platform has it (else ``spawn``): never ``fork``, which copies a
process whose threads (torch's pools) may hold locks.

Example:
    >>> w = Writer(0)            # no worker processes: every object is written at once, here
    >>> w.workers
    0
"""
from __future__ import annotations

import multiprocessing as mp
import os
import threading
import time
from collections import deque
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import torch

from ..marching import occupancy_to_meshes
from ..mesh import largest_component
from ..runtime import LeanProcessPool, cores, env_count, start_method
from . import write_worker
from .write_worker import write_object_safe

__all__ = ["Writer", "writer_workers", "start_method", "canvas_to_image_4x4", "proposals_payload", "id_array",
           "INT64_RANGE", "mesh_jobs"]


def writer_workers(stage: str = "all", device: torch.device | None = None) -> int:
    """Writer processes of a run: ``CARVI_WRITERS`` if set, else ``cores - 1`` (at least 1; at
    most 8 on the CPU, 16 with ``device`` a GPU; none for ``stage=cameras``).

    On the CPU the carving needs the cores too; with a GPU the main process mostly waits on the
    device, and the writers are what limits a run (docs/benchmarks.md).
    """
    env = env_count("CARVI_WRITERS", 0)
    if env is not None:
        return env
    if stage != "all":
        return 0
    cap = 16 if device is not None and device.type == "cuda" else 8
    return min(cap, max(1, cores() - 1))


def canvas_to_image_4x4(scale: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """``(4, 4)`` float64 map of camera-frame points from canvas pixels to image pixels (x, y shifted and
    scaled, z scaled), for a canvas similarity ``canvas = scale * image + offset``.

    Example:
        >>> canvas_to_image_4x4(torch.tensor(2.0), torch.tensor([4.0, 0.0]))[0].tolist()
        [0.5, 0.0, 0.0, -2.0]
    """
    a = float(scale)
    T = torch.eye(4, dtype=torch.float64)
    T[0, 0] = T[1, 1] = T[2, 2] = 1.0 / a
    T[0, 3] = -float(offset[0]) / a
    T[1, 3] = -float(offset[1]) / a
    return T


#: The integers an int64 array holds (a larger integer id is written as a string, as written in the input).
INT64_RANGE = (-2 ** 63, 2 ** 63 - 1)


def id_array(ids: list, missing=-1) -> np.ndarray:
    """Annotation ids as an array a ``.npz`` holds without pickling: int64 when every id is an integer
    that int64 holds, else strings (``missing`` becomes ``""``; an integer beyond 64 bits keeps its digits).

    Example:
        >>> id_array([3, -1]).dtype.kind, id_array(["a", -1]).tolist(), id_array([10 ** 30, 3]).tolist()
        ('i', ['a', ''], ['1000000000000000000000000000000', '3'])
    """
    lo, hi = INT64_RANGE
    if all(isinstance(i, int) and lo <= i <= hi for i in ids):
        return np.asarray(ids, dtype=np.int64)
    return np.asarray(["" if i == missing else str(i) for i in ids], dtype=str)


def proposals_payload(sel, j: int, surrogates: torch.Tensor | None, canvas_to_image: torch.Tensor,
                      aid_of: list) -> dict:
    """Every proposal of reference ``j`` of a chunk's :class:`~carvi_torch.select.Selection`, for
    ``<class>/proposals/<id>.npz`` (bit-packed occupancy, image-pixel transforms, scores)."""
    R, P = sel.scores.shape
    positions = sel.pos[j * P:(j + 1) * P]
    ok = positions >= 0
    idx = positions.clamp(min=0).to(sel.grids.occupancy.device)
    occ = sel.grids.occupancy[idx].cpu().numpy() & ok.numpy()[:, None, None, None]
    v2img = (canvas_to_image[None] @ sel.grids.voxel_to_camera[idx].double().cpu()).numpy()
    pairs = surrogates[j].tolist() if surrogates is not None else [[-1, -1]] * P
    sur = id_array([aid_of[x] if x >= 0 else -1 for pair in pairs for x in pair]).reshape(P, 2)
    return dict(occupancy_bits=np.packbits(occ.reshape(P, -1), axis=1), shape=np.asarray(occ.shape[1:]),
                voxel_to_camera=v2img, valid=ok.numpy(), scores=sel.scores[j].numpy(),
                misses=sel.misses[j].numpy(), best=np.int64(sel.best[j]), surrogates=sur)


def mesh_jobs(occupancy: torch.Tensor, host: torch.Tensor, jobs: list[dict], largest: bool, mesh_format: str) -> None:
    """Mesh a chunk's selected grids in one batch on their device (:mod:`carvi_torch.marching`) into its
    writer ``jobs`` (``mesh_vertices``, ``mesh_faces``): the writers then only write.

    ``occupancy``: the chunk's selected grids ``(R, D, H, W)`` bool (puffballs included), meshed where they
    lie; ``host``: the same grids on the host. ``largest``: keep the largest component first, on the host
    copy, as the writers would (the jobs' occupancy becomes it). A PLY file holds float32 vertices and int32
    faces: they are sent so (fewer bytes to the writers, the same file)."""
    occ = occupancy
    if largest:
        kept = largest_component(host.numpy())
        for job, o in zip(jobs, kept):
            job["occupancy"], job["largest_component"] = o, False
        occ = torch.from_numpy(kept).to(occupancy.device)
    v2img = torch.from_numpy(np.stack([job["voxel_to_image"] for job in jobs]))
    vertex_type = torch.float32 if mesh_format == "ply" else torch.float64
    for job, (verts, faces) in zip(jobs, occupancy_to_meshes(occ, v2img, vertex_dtype=vertex_type,
                                                              face_dtype=torch.int32)):
        job["mesh_vertices"], job["mesh_faces"] = verts, faces


class Writer:
    """Meshes and files of reconstructed objects, in worker processes or inline.

    Results are booked in submission order (deterministic reports). At most
    ``4 * workers`` objects wait at once (or the ``backlog`` a submission allows: a chunk of objects handed
    over at once), which bounds the memory of pending grids.
    With ``workers == 0`` every object is written at once, in this process.
    ``blocked``: seconds :meth:`submit` spent waiting for a writer to finish (back-pressure:
    the writers, not the device work, then limit the run).

    The processes start in a thread of their own (a forkserver that imports numpy, SciPy, scikit-image
    and trimesh, then the workers): beside the run's first stages rather than before them; :attr:`pool`
    waits for them.
    """

    #: What a job runs (a module-level function, so that worker processes can import it).
    write = staticmethod(write_object_safe)

    def __init__(self, workers: int):
        self.workers = int(workers)
        self._pool: ProcessPoolExecutor | None = None
        self._start_error: BaseException | None = None
        self.pending: deque = deque()
        self.blocked = 0.0
        self.peak_rss_mb: float | None = None  # the largest writer process's peak memory, as they report it
        self._starting = None
        if self.workers > 0:
            self._starting = threading.Thread(target=self._start, name="carvi-writers-start", daemon=True)
            self._starting.start()

    def _start(self) -> None:
        """Start the worker processes, every one of them (the thread of :meth:`__init__`)."""
        try:
            ctx = mp.get_context(start_method())
            if start_method() == "forkserver":
                ctx.set_forkserver_preload([write_worker.__name__, "trimesh"])  # what every object needs
            self._pool = LeanProcessPool(self.workers, mp_context=ctx, initializer=write_worker.init_worker,
                                         initargs=(os.getpid(),))
            for f in [self._pool.submit(write_worker.start_worker) for _ in range(self.workers)]:
                f.result()
        except BaseException as e:  # noqa: BLE001 - raised again by `pool`, in the run's thread
            self._start_error = e

    @property
    def pool(self) -> ProcessPoolExecutor | None:
        """The worker processes (``None``: written inline), once started. A failed start is raised on every
        access: nothing is ever written inline in their place without saying so."""
        if self._starting is not None:
            self._starting.join()
            self._starting = None
            if self._start_error is not None and self._pool is not None:
                self._pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
        if self._start_error is not None:
            raise self._start_error
        return self._pool

    def submit(self, job: dict, done, backlog: int = 0) -> None:
        """Write ``job`` (:func:`~carvi_torch.io.write_worker.write_object`); ``done(result)`` is called
        when it is booked. Waits first while more than ``max(4 * workers, backlog)`` objects are pending."""
        if self.pool is None:
            done(self.write(job))
            return
        self.pending.append((self.pool.submit(self.write, job), done))
        limit = max(4 * self.workers, backlog)
        if len(self.pending) > limit:
            t0 = time.perf_counter()
            while len(self.pending) > limit:
                self._finish_one()
            self.blocked += time.perf_counter() - t0

    def _finish_one(self) -> None:
        future, done = self.pending.popleft()
        try:
            out = future.result()
        except Exception as e:  # noqa: BLE001 - a writer process died (BrokenProcessPool, ...)
            out = dict(ok=False, reason=f"writer process failed: {type(e).__name__}: {e}", mesh_seconds=0.0,
                       write_seconds=0.0)
        if out.get("peak_rss_mb") is not None:
            self.peak_rss_mb = max(self.peak_rss_mb or 0.0, out["peak_rss_mb"])
        done(out)

    def drain(self) -> None:
        """Wait for every submitted object and book it."""
        while self.pending:
            self._finish_one()

    def close(self, cancel: bool = False) -> None:
        """Book what is pending (or, with ``cancel``, drop it: an error or Ctrl-C is on its way
        out) and stop the processes."""
        try:
            if not cancel:
                self.drain()
        finally:
            self.pending.clear()
            try:
                pool = self.pool
            except BaseException:  # noqa: BLE001 - the processes never started: nothing to stop
                if not cancel:
                    raise
                pool = None
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
                self._pool = None
