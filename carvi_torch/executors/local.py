"""The local executor: every class in this process, meshes and files in writer processes beside it.

Example:
    >>> from carvi_torch.config import Config
    >>> import tempfile
    >>> cfg = Config().override({"out": tempfile.mkdtemp(), "procedural_instances": 4, "classes": "car",
    ...                          "stage": "cameras", "progress": False, "preview": False})
    >>> run(cfg)["classes"]["car"]["status"]
    'cameras'
"""
from __future__ import annotations

import pickle
import platform
import traceback
from concurrent.futures.process import BrokenProcessPool
from typing import Callable

import torch

from ..config import Config
from ..io.results import ClassReport
from ..io.writer import Writer, writer_workers
from ..pipeline import class_viewpoints, run_class
from ..runtime import intra_op_threads, log, log_to_file, log_to_terminal, torch_threads
from .ahead import Ahead, AheadProcesses, result
from .common import RunSetup, announce, book_class, class_generator, finish_run, open_run

__all__ = ["run", "local_record"]


def run(cfg: Config, workers: int | None = None, threads: int | None = None) -> dict:
    """Run every class; write ``config.yaml``, ``run.log``, ``summary.json``, the class folders and
    ``preview.png`` into ``cfg.out``; return the summary.

    ``workers``: writer processes (default :func:`~carvi_torch.io.writer.writer_workers`);
    ``threads``: torch intra-op threads during the run (default :func:`~carvi_torch.runtime.intra_op_threads`;
    restored afterwards). User errors raise :class:`~carvi_torch.config.ConfigError` (or
    :class:`~carvi_torch.io.coco.CocoFormatError`) before anything is written.
    """
    with log_to_terminal(quiet=not cfg.progress):
        setup = open_run(cfg)
        with setup.lock, log_to_file(setup.out / "run.log"):
            announce(setup)
            writer = Writer(writer_workers(cfg.stage, setup.device) if workers is None else workers)
            n = intra_op_threads(writer.workers, setup.device) if threads is None else max(1, int(threads))
            setup.summary["torch_threads"] = n
            setup.summary["executor"] = local_record(len(setup.loaded.collections))
            try:
                with torch_threads(n):
                    _classes(setup, writer)
                writer.drain()
                summary = finish_run(setup, writer.workers, writer.peak_rss_mb, pool=writer.pool)
            except BaseException:
                writer.close(cancel=True)  # an error or Ctrl-C: stop the writers without waiting for them
                raise
            writer.close()
            return summary


def local_record(classes: int) -> dict:
    """``summary.json["executor"]`` of a local run, with the fields a Ray run records (README, *On a cluster*): one
    node, this machine (its host name); one task per class run; no retries (nothing runs twice here).

    Example:
        >>> rec = local_record(4); rec["name"], rec["address"], len(rec["nodes"]), rec["tasks"], rec["retries"]
        ('local', None, 1, 4, 0)
    """
    return {"name": "local", "address": None, "nodes": [platform.node() or "localhost"], "tasks": classes,
            "retries": 0}


def _classes(setup: RunSetup, writer: Writer) -> None:
    """The classes in name order. With ``viewpoint_processes`` the viewpoint stages of the next classes are made
    in worker processes; else with ``pipeline_classes`` on the CPU the next class's viewpoints are made on a
    background thread while the class before it carves (:mod:`~carvi_torch.executors.ahead`)."""
    keys = sorted(setup.loaded.collections)
    ahead, depth = _ahead(setup, len(keys))
    try:
        made: dict = {}
        for i, key in enumerate(keys):
            for k in keys[i:i + depth + 1] if ahead is not None else ():  # this class and `depth` after it
                if k not in made:
                    made[k] = _make_ahead(setup, ahead, k)
            _one_class(setup, writer, key, made.pop(key, None))
    except BaseException:
        if ahead is not None:
            ahead.close(cancel=True)  # the viewpoints in progress write nothing: left to end on their own
        raise
    if ahead is not None:
        ahead.close()


def _ahead(setup: RunSetup, classes: int) -> tuple[Ahead | AheadProcesses | None, int]:
    """Who makes the classes' viewpoints ahead of their carving, and how many classes ahead: ``viewpoint_processes``
    worker processes, else (``pipeline_classes``, on the CPU only: on a GPU both threads would share one stream
    and the free memory that sizes the chunks) one background thread, else no one."""
    cfg = setup.cfg
    if cfg.viewpoint_processes > 0 and classes > 1:
        n = min(cfg.viewpoint_processes, classes)
        return AheadProcesses(n, torch.get_num_threads()), n
    if cfg.pipeline_classes and classes > 1 and setup.device.type == "cpu":
        return Ahead(torch.get_num_threads()), 1
    return None, 0


def _make_ahead(setup: RunSetup, ahead: Ahead | AheadProcesses | None, key: str) -> tuple[torch.Generator, Callable]:
    """Class ``key``'s generator and a call that returns its :func:`~carvi_torch.pipeline.class_viewpoints`, made
    on ``ahead``. Where the worker processes cannot take the class (a worker died: :class:`BrokenProcessPool`;
    the class would not pickle) or lose it, its viewpoints are made in this process, and the run goes on."""
    coll, cfg, generator = setup.loaded.collections[key], setup.cfg, class_generator(setup.cfg, key)
    args = (coll, cfg, setup.device, generator, setup.gt)
    if isinstance(ahead, Ahead):
        return generator, ahead.submit(class_viewpoints, *args).result
    try:
        futures = [ahead.submit(coll, cfg, setup.gt)]
    except (BrokenProcessPool, RuntimeError, pickle.PicklingError) as e:
        log.warning(f"{key}: no viewpoint process can take it ({type(e).__name__}: {e}); making its viewpoints here")
        return generator, lambda: class_viewpoints(*args)

    def finish() -> tuple:
        try:
            made = result(futures.pop())  # the pickled result is let go of once read
        except BrokenProcessPool as e:
            log.warning(f"{key}: the viewpoint process stopped ({e}); making its viewpoints here")
            made = None
        return class_viewpoints(*args, made=made)

    return generator, finish


def _one_class(setup: RunSetup, writer: Writer, key: str, made: tuple[torch.Generator, Callable] | None) -> None:
    """Run class ``key`` (its viewpoints ``made`` ahead, or here) and book it; a class that fails (its viewpoints
    ahead included) is booked with its reason and the run goes on."""
    coll = setup.loaded.collections[key]
    log.info(f"{key}: {len(coll)} objects")
    try:
        generator, early = (class_generator(setup.cfg, key), None) if made is None else (made[0], made[1]())
        rep = run_class(coll, setup.cfg, setup.out, setup.gt, setup.device, generator, writer, ahead=early)
    except Exception as e:  # noqa: BLE001 - one broken class must not stop the others
        rep = ClassReport(key, objects=len(coll), status="failed")
        rep.skip(f"{type(e).__name__}: {e}", "class")
        log.error(f"{key}: failed: {type(e).__name__}: {e}")
        log.debug(traceback.format_exc())
    book_class(setup, key, rep)
