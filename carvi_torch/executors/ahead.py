"""One class ahead: the next class's viewpoints made on a background thread while this class carves.

The local executor runs the classes one after the other. With ``pipeline_classes`` (on the CPU) a background
thread makes class ``i + 1``'s :func:`~carvi_torch.pipeline.class_viewpoints` (SfM, the mixture of
shapes, refinement, the canonical frame, the surrogate plan: hundreds of operations on small tensors
that hold one core) while the run's thread carves, selects and hands class ``i`` to the writers
(large operations, which release the GIL). That part reads and writes no file and draws only on the
class's own generator (:func:`~carvi_torch.executors.common.class_generator`), so the outputs are the
sequential run's; the rest of each class (the resume check, ``cameras.json``, the silhouettes, the
carving) and its booking into ``summary.json`` stay on the run's thread, in class order. At most one
class is made ahead: one class's viewpoints more in memory.

Threads: with OpenMP (torch's CPU backend) the intra-op thread count is a per-thread setting, and a
parallel operation splits its sums by it; the background thread sets the run's count for itself, so
that every operation runs as it does in the sequential run (the solvers inside set one thread for
themselves either way). Each Python thread gets its own team of intra-op threads.

With ``viewpoint_processes`` (:class:`AheadProcesses`) worker processes make the viewpoint stages
(:func:`~carvi_torch.pipeline.viewpoint_stage`) of several classes at once, on the CPU, each process with the
run's torch thread count; the run's thread takes each result in class order and finishes the class's
:func:`~carvi_torch.pipeline.class_viewpoints` (the move to its device, the surrogate plan) itself. A class
and its result travel pickled; a worker reads and writes no file.

Example:
    >>> ahead = Ahead(threads=1)
    >>> ahead.submit(sum, [1, 2, 3]).result()
    6
    >>> ahead.close()
"""
from __future__ import annotations

import multiprocessing as mp
import pickle
import queue
import threading
from concurrent.futures import Future
from typing import Callable

from ..runtime import LeanProcessPool, ignore_interrupt

__all__ = ["Ahead", "AheadProcesses"]


class Ahead:
    """A background thread that runs the calls submitted to it one at a time, in order.

    :meth:`close` with ``cancel`` (an error or Ctrl-C on its way out) cancels the calls not started and
    returns at once; the call in progress, which writes nothing, runs to its end on the thread. The
    thread is not a daemon: the interpreter waits for it at exit (a daemon thread stopped inside a
    torch operation at exit aborts the process instead of letting it exit with its status).
    """

    def __init__(self, threads: int):
        self._calls: queue.SimpleQueue = queue.SimpleQueue()
        self._futures: list[Future] = []
        self._thread = threading.Thread(target=self._serve, args=(max(1, int(threads)),), name="carvi-class-ahead")
        self._thread.start()

    def submit(self, fn: Callable, *args, **kwargs) -> Future:
        """Run ``fn(*args, **kwargs)`` after the calls submitted before; its result (or exception) in the future."""
        future: Future = Future()
        self._futures = [f for f in self._futures if not f.done()] + [future]
        self._calls.put((future, fn, args, kwargs))
        return future

    def _serve(self, threads: int) -> None:
        import torch

        torch.set_num_threads(threads)  # this thread's own count (OpenMP): the run's
        while True:
            call = self._calls.get()
            if call is None:
                return
            future, fn, args, kwargs = call
            del call
            if future.set_running_or_notify_cancel():
                try:
                    future.set_result(fn(*args, **kwargs))
                except BaseException as e:  # noqa: BLE001 - raised again by future.result(), in the run's thread
                    future.set_exception(e)
            del future, fn, args, kwargs  # the class's data is the caller's from here on

    def close(self, cancel: bool = False) -> None:
        """Stop the thread: once the submitted calls have run (joined), or with ``cancel`` at once."""
        if cancel:
            for f in self._futures:
                f.cancel()
        self._calls.put(None)
        if not cancel:
            self._thread.join()


class AheadProcesses:
    """Worker processes (started with ``spawn``, without the run's main module) that run
    :func:`~carvi_torch.pipeline.viewpoint_stage` on classes submitted to them, several at once, with
    ``threads`` torch threads each. :meth:`submit` returns a future of the pickled ``(vp, report)``
    (:func:`result`). ``close(cancel=True)`` cancels the classes not started and stops the processes (they write
    nothing). The processes ignore Ctrl-C (SIGINT, which a terminal sends to the whole process group): the run
    handles it and stops them."""

    def __init__(self, processes: int, threads: int):
        self._pool = LeanProcessPool(max(1, int(processes)), mp_context=mp.get_context("spawn"),
                                     initializer=_init_process, initargs=(max(1, int(threads)),))

    def submit(self, coll, cfg, gt: dict | None = None) -> Future:
        """Make ``coll``'s viewpoint stage under ``cfg`` (``gt``: the ground truth, sent only with
        ``cameras=gt``) in a worker process, on the CPU."""
        gt = gt if cfg.study.cameras == "gt" else None
        return self._pool.submit(_stage_in_process, pickle.dumps((coll.to("cpu"), cfg, gt), pickle.HIGHEST_PROTOCOL))

    def close(self, cancel: bool = False) -> None:
        """Stop the processes: once every submitted class is made (joined), or with ``cancel`` at once (the
        classes in progress are dropped: otherwise the interpreter's exit would wait for them)."""
        if cancel:
            self._pool.stop()
        else:
            self._pool.shutdown(wait=True)


def result(future: Future) -> tuple:
    """The ``(vp, report)`` of a class submitted to :class:`AheadProcesses` (its exception raised again)."""
    return pickle.loads(future.result())


def _init_process(threads: int) -> None:
    import torch

    ignore_interrupt()  # Ctrl-C is the run's to handle (close(cancel=True))
    torch.set_num_threads(threads)


def _stage_in_process(payload: bytes) -> bytes:
    """In a worker process: :func:`~carvi_torch.pipeline.viewpoint_stage` of the pickled ``(coll, cfg, gt)``,
    its ``(vp, report)`` pickled (plain pickle: tensors travel as bytes, not as shared memory)."""
    from ..pipeline import viewpoint_stage

    coll, cfg, gt = pickle.loads(payload)
    return pickle.dumps(viewpoint_stage(coll, cfg, gt), pickle.HIGHEST_PROTOCOL)
