"""Build the report of a finished run: ``OUT/index.html``, ``OUT/cards.js``, ``OUT/assets/``,
``OUT/classes/<class>.png``, ``OUT/objects/<class>/<stem>.{jpg,js}``; nothing outside ``OUT``. Every file is
written to a temporary name in its folder and moved into place (:func:`carvi_torch.io.outputs.write_within`):
nothing is written through a symbolic link, and one among the report's entries is refused before any work.

Cards are sorted worst first (:data:`SortBy`): by ``quality`` ascending when the run scored its
objects, else by the selected proposal's score descending (a disagreement with the class's average
silhouettes: higher is worse) when the run kept the scores, else by the silhouette IoU ascending.
Skipped objects and objects with damaged files come first.

Example:
    >>> from carvi_torch.report.cards import Card
    >>> cards = [Card("1", "c", "c/1", iou=0.9), Card("2", "c", "c/2", iou=0.5), Card("3", "c", "c/3", skipped="x")]
    >>> order, by = sort_cards(cards)
    >>> [c.id for c in order], by
    (['3', '2', '1'], 'iou')
"""
from __future__ import annotations

import contextlib
import io
import json
import logging
import multiprocessing as mp
import os
import time
from dataclasses import dataclass
from pathlib import Path
from concurrent.futures.process import BrokenProcessPool
from typing import Literal

from ..io.coco import class_keys
from ..io.layout import objects_made_otherwise, settings_record
from ..io.outputs import first_link, folder_within, safe_name, write_within
from ..runtime import LeanProcessPool, check_replaceable, os_error_line, start_method
from .cards import Card, CardContext, ClassView, add_mesh, card_without_mesh, failed_card, make_card
from .charts import class_figure
from .inputs import ReportError, RunInputs, read_run
from .mesh_data import write_mesh_script
from .page import class_panel_html, index_html

__all__ = ["build_report", "start_report", "PendingReport", "sort_cards", "default_workers", "Report", "SortBy",
           "STATIC", "ASSETS", "POOL_FROM"]

log = logging.getLogger(__name__)
#: Runs with at least this many objects make their cards in worker processes (:func:`default_workers`).
POOL_FROM = 100
#: The number cards are sorted by, worst first.
SortBy = Literal["quality", "score", "iou"]
#: The package's static files, and those copied into ``OUT/assets``.
STATIC = Path(__file__).resolve().parent / "static"
ASSETS = {"report.js": "report.js", "report.css": "report.css", "vendor/three.min.js": "three.min.js",
          "vendor/OrbitControls.js": "OrbitControls.js", "vendor/LICENSE.three.txt": "LICENSE.three.txt",
          "vendor/VENDOR.md": "VENDOR.md"}


@dataclass
class Report:
    """What :func:`build_report` made."""

    index: Path
    cards: int
    sort_by: SortBy
    seconds: float


def sort_cards(cards: list[Card]) -> tuple[list[Card], SortBy]:
    """``cards`` worst first, and the number that ordered them (see the module docstring)."""
    by: SortBy = ("quality" if any(c.quality is not None for c in cards)
                  else "score" if any(c.score is not None for c in cards) else "iou")
    sign = -1.0 if by == "score" else 1.0

    def key(c: Card):
        v = getattr(c, by)
        return (c.skipped is None and not c.problems, v is not None, sign * v if v is not None else 0.0)

    return sorted(cards, key=key), by


def _context(recon: Path, out: Path, data: Path | None, mesh_format: str, max_faces: int) -> CardContext:
    anns, images, coco, problem, ann_class = {}, {}, None, None, {}
    if data is None:
        problem = "summary.json names no input annotation file: no overlay"
    else:
        try:
            from pycocotools.coco import COCO

            with contextlib.redirect_stdout(io.StringIO()):  # pycocotools prints progress lines
                coco = COCO(str(data))
            anns = {str(k): v for k, v in coco.anns.items()}
            images = coco.imgs
            key_of = class_keys(coco.dataset.get("categories", []))
            ann_class = {k: key_of.get(str(a.get("category_id"))) for k, a in anns.items()}
        except Exception as e:  # noqa: BLE001 - no overlays, every card says why
            problem = f"input annotations {data.name} unreadable ({type(e).__name__}): no overlay"
    return CardContext(recon=recon, out=out, anns=anns, images=images, coco=coco, data=data,
                       mesh_format=mesh_format, max_faces=max_faces, data_problem=problem, ann_class=ann_class)


_WORKER_CTX: CardContext | None = None


def _init_worker(*args) -> None:
    global _WORKER_CTX
    _WORKER_CTX = _context(*args)


def _card_in_worker(job: tuple) -> Card:
    return make_card(_WORKER_CTX, *job)


def default_workers(n_objects: int) -> int:
    """Card processes for a run of ``n_objects``: none below :data:`POOL_FROM` objects (starting them
    costs more than it saves) or on 2 cores or fewer (measured slower there, docs/report.md), else
    one per core but one, at most 4."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return 0 if n_objects < POOL_FROM or cores <= 2 else min(4, cores - 1)


def _jobs(run: RunInputs) -> list[tuple[ClassView, object, str]]:
    """Every object's card job ``(class view, object, output folder key)``, classes in order."""
    return [(ClassView.of(c), o, safe_name(c.key)) for c in run.classes for o in c.objects]


def _make_cards(run: RunInputs, out: Path, max_faces: int, workers: int | None) -> list[Card]:
    """Every object's card (written files included), in the order of :func:`_jobs`, in this process or in
    ``workers`` processes."""
    args = (run.recon, out, run.data, run.mesh_format, max_faces)
    jobs = _jobs(run)
    workers = default_workers(len(jobs)) if workers is None else workers
    if workers > 0:
        try:
            with LeanProcessPool(workers, mp_context=mp.get_context(start_method()), initializer=_init_worker,
                                 initargs=args) as pool:
                return list(pool.map(_card_in_worker, jobs, chunksize=max(1, min(32, len(jobs) // (4 * workers)))))
        except (OSError, BrokenProcessPool) as e:  # no worker processes here: make the cards in this one
            log.warning(f"report: worker processes failed ({type(e).__name__}: {e}); making the cards here")
    ctx = _context(*args)
    return [make_card(ctx, *job) for job in jobs]


def _cards_beside(ctx: CardContext, jobs: list, meshes: list) -> tuple[list[Card], list]:
    """Every object's card made in this process but for its mesh script, which ``meshes`` (per job of :func:`_jobs`)
    holds the future of (:func:`~carvi_torch.report.mesh_data.write_mesh_script` in another process, or ``None``).
    Returns the cards and, per card, ``(job, script arguments, future)`` for :func:`_book_meshes` (``None``: no
    script)."""
    cards, pending = [], []
    for (view, obj, key), future in zip(jobs, meshes):
        card, args = card_without_mesh(ctx, view, obj, key)
        cards.append(card)
        pending.append(None if args is None else ((view, obj, key), args, future))
    return cards, pending


def _book_meshes(cards: list[Card], pending: list) -> None:
    """Book every mesh script of :func:`_cards_beside` on its card (waiting for it); one whose process failed is
    made here; a card whose script cannot be made at all becomes a failed card, as :func:`make_card` makes it."""
    for i, item in enumerate(pending):
        if item is None:
            continue
        (view, obj, key), args, future = item
        try:
            try:
                made = future.result() if future is not None else write_mesh_script(*args)
            except Exception:  # noqa: BLE001 - the process failed (BrokenProcessPool, ...): made here
                made = write_mesh_script(*args)
            add_mesh(cards[i], args, made)
        except Exception as e:  # noqa: BLE001 - one object's failure is its card's reason, never the report's end
            cards[i] = failed_card(view, obj, key, e)


def _submit_meshes(pool, run: RunInputs, out: Path, max_faces: int) -> list:
    """Hand every mesh script of the report to ``pool`` (an executor); per job of :func:`_jobs` its future, or
    ``None`` where the object is skipped or has no mesh file (the card says why) or the pool refused the job (a
    broken pool: from then on every script is made in this process)."""
    from ..io.layout import object_mesh

    futures = []
    for view, obj, key in _jobs(run):
        src = None if obj.skipped is not None else object_mesh(run.recon / view.key, obj.annotation_id,
                                                                run.mesh_format)
        future = None
        if src is not None and pool is not None:
            try:
                future = pool.submit(write_mesh_script, str(src), str(out), f"objects/{key}/{obj.stem}.js",
                                     f"{key}/{obj.stem}", max_faces)
            except Exception as e:  # noqa: BLE001 - BrokenProcessPool, a shut-down pool: made here
                log.warning(f"report: the worker processes refused the mesh scripts ({type(e).__name__}: {e}); "
                            "making them here")
                pool = None
        futures.append(future)
    return futures


def _copy_assets(out: Path) -> None:
    for src, dst in ASSETS.items():
        write_within(out, f"assets/{dst}", (STATIC / src).read_bytes(), sync=False)


#: What a report writes in its folder: a folder holding only these is an earlier report (replaced).
REPORT_NAMES = frozenset({"index.html", "cards.js", "assets", "classes", "objects"})
#: The files written in the folder itself: a temporary ``.<name>.<random>.tmp`` of one (left by a report
#: killed while writing it) belongs to a report too.
TOP_FILES = ("index.html", "cards.js")


def _not_report(out: Path) -> list[str]:
    """The entries of the folder ``out`` that no report writes."""
    def ours(name: str) -> bool:
        return name in REPORT_NAMES or (name.endswith(".tmp") and name.startswith(tuple(f".{n}." for n in TOP_FILES)))

    return [p.name for p in out.iterdir() if not ours(p.name)]


def _prepare(out: Path, run: RunInputs) -> None:
    """Refuse an ``out`` that cannot take the report (see :func:`build_report`), then make it and the folders
    the cards write into."""
    check_replaceable(out, _not_report, "an earlier report", ReportError)
    link = first_link(out, sorted(REPORT_NAMES)) if out.is_dir() else None
    if link is not None:
        raise ReportError(f"--out {out}: {link.relative_to(out).as_posix()!r} is a symbolic link; the report never "
                          "writes through one: remove it or choose another --out (nothing was written)")
    try:
        out.mkdir(parents=True, exist_ok=True)
        for cls in run.classes:
            folder_within(out, f"objects/{safe_name(cls.key)}")
    except OSError as e:
        raise ReportError(f"cannot make --out {out}: {os_error_line(e, said=out)}") from e


def build_report(recon: str | Path, out: str | Path | None = None, per_page: int = 24, max_faces: int = 4000,
                 title: str | None = None, workers: int | None = None) -> Report:
    """Write the report of the run in ``recon`` into ``out`` (default ``recon/report``).

    ``max_faces``: the 3D views' meshes are decimated to at most this many faces; ``workers``: card
    processes (default :func:`default_workers`; 0: all in this process).

    Raises:
        carvi_torch.report.inputs.ReportError: ``recon`` has no readable ``summary.json``, or ``out`` is
            the run's folder, a class folder, a folder holding anything but an earlier report or a symbolic link
            among the report's entries (nothing is written through a link), or cannot be made.
    """
    return start_report(recon, out, per_page, max_faces, title, workers).finish()


def start_report(recon: str | Path, out: str | Path | None = None, per_page: int = 24, max_faces: int = 4000,
                 title: str | None = None, workers: int | None = None, pool=None) -> "PendingReport":
    """:func:`build_report` in two steps: this one reads the run and prepares ``out`` (raising what
    :func:`build_report` raises) and, given ``pool`` (an executor, such as a run's writer processes), hands it
    every mesh script (``workers`` is then not used); :meth:`PendingReport.finish` makes the rest in this process.
    The caller may do other work in between (a run draws its ``preview.png``) while the pool decimates the
    meshes; the files are those of :func:`build_report`."""
    t0 = time.perf_counter()
    run = read_run(recon)
    if out is None and (run.recon / "report").is_symlink():  # as reconstruct refuses it: the run writes only inside
        raise ReportError(f"{run.recon / 'report'} is a symbolic link: the report writes only inside the run's folder; "
                          "remove the link or give --out (nothing was written)")
    out = Path(out) if out is not None else run.recon / "report"
    if out.resolve() == run.recon.resolve() or out.resolve() in {(run.recon / c.key).resolve() for c in run.classes}:
        raise ReportError(f"--out {out} is the run's folder or a class folder: give the report a folder of its own")
    _prepare(out, run)
    meshes = _submit_meshes(pool, run, out, max_faces) if pool is not None else None
    return PendingReport(run, out, per_page, max_faces, title, workers, t0, meshes)


@dataclass
class PendingReport:
    """A report :func:`start_report` began; :meth:`finish` writes it."""

    run: RunInputs
    out: Path
    per_page: int
    max_faces: int
    title: str | None
    workers: int | None
    t0: float
    meshes: list | None
    """Per card job, the future of its mesh script in the pool (``None``: none); ``None``: no pool."""

    def finish(self) -> Report:
        """Make the cards (their mesh scripts booked from the pool), the class figures, ``cards.js``, the assets
        and ``index.html``."""
        run, out = self.run, self.out
        jobs, pending = _jobs(run), None
        if self.meshes is None:
            cards = _make_cards(run, out, self.max_faces, self.workers)
        else:
            ctx = _context(run.recon, out, run.data, run.mesh_format, self.max_faces)
            cards, pending = _cards_beside(ctx, jobs, self.meshes)
        panels, names = [], []
        for cls in run.classes:
            mine = [card for (view, _, _), card in zip(jobs, cards) if view.key == cls.key]
            panels.append(class_panel_html(cls.summary, cls.key, cls.name, _figure(mine, out, cls.key), cls.problem))
            names.append((cls.key, cls.name))
        if pending is not None:  # the figures need no mesh: drawn while the pool still decimates
            _book_meshes(cards, pending)
        order, by = sort_cards(cards)
        meta = {"per_page": self.per_page, "sort_by": by, "names": dict(names)}
        write_within(out, "cards.js", ("carviReport.index(" + json.dumps(meta) + ",\n["
                                       + ",\n".join(json.dumps(c.to_json()) for c in order) + "]);\n").encode(),
                     sync=False)
        _copy_assets(out)
        title = self.title or f"carvi_torch report: {run.recon.resolve().name}"
        mixed = settings_record(run.summary.get("resumed_from_other_settings"))  # objects counted only then
        page = index_html(run.summary, title, panels, names, len(order), by,
                          objects_made_otherwise(run.recon) if mixed else None)
        index = write_within(out, "index.html", page.encode(), sync=False)
        return Report(index=index, cards=len(order), sort_by=by, seconds=time.perf_counter() - self.t0)


def _figure(cards: list[Card], out: Path, class_key: str) -> str | None:
    """The class figure of ``cards`` (:func:`~carvi_torch.report.charts.class_figure`) as ``out/classes/<key>.png``;
    its path relative to ``out``, or ``None`` for a class without cards or a figure that failed (a warning)."""
    if not cards:
        return None
    rel = f"classes/{safe_name(class_key)}.png"
    try:
        class_figure(cards, out, rel)
        return rel
    except Exception as e:  # noqa: BLE001 - a figure that fails leaves its panel without it
        log.warning(f"report: the figure of class {class_key} failed ({type(e).__name__}: {e})")
        return None
