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

import traceback

from ..config import Config
from ..io.results import ClassReport
from ..io.writer import Writer, writer_workers
from ..pipeline import run_class
from ..runtime import intra_op_threads, log, log_to_file, log_to_terminal, torch_threads
from .common import RunSetup, announce, book_class, class_generator, finish_run, open_run

__all__ = ["run"]


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
        with log_to_file(setup.out / "run.log"):
            announce(setup)
            writer = Writer(writer_workers(cfg.stage, setup.device) if workers is None else workers)
            n = intra_op_threads(writer.workers) if threads is None else max(1, int(threads))
            setup.summary["torch_threads"] = n
            setup.summary["executor"] = {"name": "local", "address": None}
            try:
                with torch_threads(n):
                    _classes(setup, writer)
            except BaseException:
                writer.close(cancel=True)  # an error or Ctrl-C: stop the writers without waiting for them
                raise
            writer.close()
            return finish_run(setup, writer.workers, writer.peak_rss_mb)


def _classes(setup: RunSetup, writer: Writer) -> None:
    cfg = setup.cfg
    for key in sorted(setup.loaded.collections):
        coll = setup.loaded.collections[key]
        log.info(f"{key}: {len(coll)} objects")
        try:
            rep = run_class(coll, cfg, setup.out, setup.gt, setup.device, class_generator(cfg, key), writer)
        except Exception as e:  # noqa: BLE001 - one broken class must not stop the others
            rep = ClassReport(key, objects=len(coll), status="failed")
            rep.skip(f"{type(e).__name__}: {e}", "class")
            log.error(f"{key}: failed: {type(e).__name__}: {e}")
            log.debug(traceback.format_exc())
        book_class(setup, key, rep)
