"""The Ray executor (``executor=ray``): a run's classes as tasks on a Ray cluster.

The split of the work (docs/distributed.md):

- :func:`prepare_task`, one per class: viewpoints (SfM and refinement need the whole class), clusters,
  triplets and prepared silhouettes; writes ``<class>/cameras.json``; returns the class plan
  (:class:`~carvi_torch.pipeline.ClassPlan`), which stays in Ray's object store, put there once per class;
- :func:`chunk_task`, one per ``ray_chunk_objects`` objects of a class: carving, selection, meshing and
  writing, straight into ``--out`` (atomic files, a shared filesystem on a cluster); the plan is its
  argument: Ray fetches it from the object store (or rebuilds it, when its node was lost) before the
  task starts, so that no task waits for it holding a CPU;
- :func:`finish_task`, one per class: the class's closing files (``cameras.json`` again when an object
  became a puffball, the merged proposal scores).

The driver (this process) reads the annotations, decides which objects an earlier run finished (resume
works across executors: the files are the same), submits the tasks, merges their reports into
``summary.json`` and records ``executor: {name, address, nodes, tasks, retries}``. A task whose worker
process or node dies is run again by Ray (``TASK_RETRIES``); a lost class plan is rebuilt by Ray from
its task (the same arguments, so the same plan); every object written before stays written.

Ray is imported only here, when a run asks for it; without it the run stops with one line that says
how to install it.
"""
from __future__ import annotations

import contextlib
import logging
import os
import socket
import tempfile
import traceback
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

from tqdm.auto import tqdm

from ..config import Config, ConfigError
from ..io.results import ClassReport
from ..pipeline import finish_class, finished_objects, prepare_class, reconstruct_chunk
from ..runtime import log, log_to_file, log_to_terminal, os_error_line, peak_rss_mb, torch_threads
from .common import RunSetup, announce, book_class, class_generator, finish_run, open_run

__all__ = ["run", "import_ray", "connect", "loopback", "environ", "is_loopback", "LOOPBACK_VAR",
           "prepare_task", "chunk_task", "finish_task",
           "TASK_RETRIES", "TASK_CPUS",
           "PLAN_BYTES_PER_PIXEL", "STORE_SHARE", "check_reachable"]

#: Times Ray runs a task again whose worker process or node died (an error the task raises is not retried:
#: it would raise again; its class is reported failed, with the reason).
TASK_RETRIES = 3
#: CPUs (and torch threads) of a task.
TASK_CPUS = 1
#: Bytes of a class plan per object and canvas pixel (a 40-object class at 128^2 pixels: 221 KB per object,
#: mostly the distance maps of the silhouettes and their mirrors).
PLAN_BYTES_PER_PIXEL = 14
#: Share of the cluster's object store the plans of the classes in flight may take together.
STORE_SHARE = 0.5


def import_ray():
    """The ``ray`` module; :class:`ConfigError` (one line: how to install it) when it is not installed."""
    try:
        import ray
    except ImportError:
        raise ConfigError("executor=ray needs Ray, which is not installed: pip install 'carvi_torch[ray]'") from None
    return ray


#: Ray's switch (an environment variable, read when Ray is imported) that makes a Ray started on this
#: machine bind to 127.0.0.1 instead of the machine's interface address.
LOOPBACK_VAR = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


@contextlib.contextmanager
def loopback():
    """Context: a Ray started on this machine meanwhile (``ray.init()``, ``ray.cluster_utils.Cluster``)
    listens on 127.0.0.1 only. Sets :data:`LOOPBACK_VAR` to ``0`` for the processes Ray starts, and the
    same switch in this process's Ray, which read the variable when it was imported; both restored after."""
    import_ray()
    from ray._private import ray_constants

    switch = ray_constants.ENABLE_RAY_CLUSTER
    ray_constants.ENABLE_RAY_CLUSTER = False
    try:
        with environ(**{LOOPBACK_VAR: "0"}):
            yield
    finally:
        ray_constants.ENABLE_RAY_CLUSTER = switch


#: Seconds to wait for a cluster's head to accept a connection before the run gives up.
CONNECT_TIMEOUT_S = 10.0

#: Seconds of each of Ray's waits for a cluster's head to answer as Ray (one try): where something else
#: listens at the address, the run gives up after about 20 s, where ``ray.init`` would keep trying for about
#: 14 minutes (20 tries of 35 s). ``RAY_py_gcs_connect_timeout_s`` / ``RAY_gcs_server_port_wait_time_s`` set
#: by the user win. Ray reads them when it is imported: a process that imported Ray before waits as Ray says.
GCS_WAIT_S = 10


def gcs_wait_env() -> dict[str, str]:
    """The Ray settings that bound the wait for a cluster's head (:data:`GCS_WAIT_S`, one try),
    leaving out those the environment already sets.

    Example:
        >>> set(gcs_wait_env()) <= {"RAY_py_gcs_connect_timeout_s", "RAY_gcs_server_port_wait_time_s"}
        True
    """
    wanted = {"RAY_py_gcs_connect_timeout_s": str(GCS_WAIT_S), "RAY_gcs_server_port_wait_time_s": "1"}
    return {k: v for k, v in wanted.items() if k not in os.environ}


def check_reachable(address: str) -> None:
    """:class:`ConfigError` unless ``host:port`` accepts a TCP connection within :data:`CONNECT_TIMEOUT_S`
    (Ray itself keeps trying for minutes); ``auto`` and other forms are left to Ray.

    Example:
        >>> check_reachable("auto")
    """
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as e:
        raise ConfigError(f"ray_address={address}: no Ray head answers there ({os_error_line(e)})") from None


@contextlib.contextmanager
def environ(**values: str | None):
    """Context: the environment variables ``values`` set (``None``: removed) meanwhile, restored after."""
    def put(pairs):
        for k, v in pairs.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v

    before = {k: os.environ.get(k) for k in values}
    try:
        put(values)
        yield
    finally:
        put(before)


#: Host names of this machine's loopback interface.
LOOPBACK_HOSTS = ("localhost", "::1")


def is_loopback(address: str | None) -> bool:
    """Whether ``address`` (``host:port``) names this machine's loopback interface.

    Example:
        >>> is_loopback("127.0.0.1:6379"), is_loopback("10.0.0.5:6379"), is_loopback("auto")
        (True, False, False)
    """
    host = (address or "").rpartition(":")[0].strip("[]")
    return host.startswith("127.") or host in LOOPBACK_HOSTS


@contextlib.contextmanager
def connect(address: str | None):
    """Ray, connected for the run; yields the cluster's address.

    This process's existing connection is used as it is. Else ``address`` (``auto`` or ``host:port``;
    a loopback ``host`` is connected to over loopback, :func:`loopback`); ``None`` starts a Ray on this
    machine for the run: loopback only, without token authentication (nothing written to
    ``~/.ray``), no dashboard, no usage report, its session files in a temporary folder removed
    afterwards, whatever ``RAY_ADDRESS`` says. A cluster that cannot be reached is a :class:`ConfigError`.
    """
    with contextlib.ExitStack() as stack:
        if address is not None:
            check_reachable(address)
            stack.enter_context(environ(**gcs_wait_env()))  # before Ray's import: it reads them then
        ray = import_ray()
        if ray.is_initialized():
            yield ray.get_runtime_context().gcs_address
            return
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        kw = dict(log_to_driver=False, logging_level=logging.WARNING)
        if address is None or is_loopback(address):
            stack.enter_context(loopback())
        if address is None:
            stack.enter_context(environ(RAY_AUTH_MODE="disabled", RAY_ADDRESS=None))
            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="carvi-ray-", ignore_cleanup_errors=True))
            kw.update(include_dashboard=False, _node_ip_address="127.0.0.1", _temp_dir=tmp)
        try:
            ray.init(address=address, **kw)
        except (ConnectionError, ValueError, RuntimeError) as e:
            raise ConfigError(f"ray_address={address}: cannot start or reach Ray: {' '.join(str(e).split())}") \
                from None
        stack.callback(ray.shutdown)
        yield ray.get_runtime_context().gcs_address


# =========================================================================== the tasks (worker processes)

def _here() -> tuple[str, int, int | None]:
    """This task's node id, CPUs, and attempt (0: its first run; ``None`` where this Ray does not tell)."""
    ray = import_ray()
    ctx = ray.get_runtime_context()
    attempt = getattr(ctx.worker.core_worker, "get_current_task_attempt_number", None)
    return (ctx.get_node_id(), max(1, int(ctx.get_assigned_resources().get("CPU", 1))),
            int(attempt()) if attempt is not None else None)


def prepare_task(coll, cfg: Config, gt: dict | None, out: str, done: list[str | None],
                 report: ClassReport | None = None):
    """Task: every stage of class ``coll`` up to carving (:func:`~carvi_torch.pipeline.prepare_class`,
    ``cameras.json`` written); ``report``: the class's report so far (the driver's resume check). Returns two
    objects: the plan, which stays in the object store, and ``(todo, report, (node, attempt, peak MB))``."""
    node, cpus, attempt = _here()
    with torch_threads(cpus):
        plan, todo, report = prepare_class(coll, cfg, cfg.resolve_device(), class_generator(cfg, coll.meta.key),
                                           gt=gt, out=Path(out), report=report, done=done)
    return plan, (todo, report, (node, attempt, peak_rss_mb()))


def chunk_task(plan, ids: list[int], cfg: Config):
    """Task: carve, select, mesh and write the originals ``ids`` of a class
    (:func:`~carvi_torch.pipeline.reconstruct_chunk`); ``plan``: the class plan (Ray reads it from the
    object store before the task starts). Returns ``(report, puffballs, (node, attempt, peak MB))``."""
    node, cpus, attempt = _here()
    with torch_threads(cpus):
        report, puffballs = reconstruct_chunk(plan, ids, cfg)
    return report, puffballs, (node, attempt, peak_rss_mb())


def finish_task(plan, cfg: Config, report: ClassReport, puffballs: list[int]):
    """Task: the end of a class (:func:`~carvi_torch.pipeline.finish_class`). Returns
    ``(report, (node, attempt, peak MB))``."""
    node, _, attempt = _here()
    finish_class(plan, cfg, report, puffballs)
    return report, (node, attempt, peak_rss_mb())


# =========================================================================== the driver


@dataclass
class _Class:
    """A class in flight: its report so far, its plan's ref, the chunks not yet back."""

    key: str
    objects: int
    report: ClassReport | None = None
    plan: object = None
    left: int = 0
    puffballs: list = field(default_factory=list)
    error: str | None = None


def _reason(e: Exception) -> str:
    """One line for a task's error: the task's own exception, or what happened to its worker or node."""
    cause = getattr(e, "cause", None)
    if isinstance(cause, BaseException):
        e = cause
    first = (str(e).strip().splitlines() or [""])[0]
    return f"{type(e).__name__}: {first}"


class _Driver:
    """Submits the tasks of every class and books what comes back. Classes start in name order while
    fewer than the cluster's CPUs + 1 are in flight and their plans (:data:`PLAN_BYTES_PER_PIXEL`) fit in
    :data:`STORE_SHARE` of the object store (one class always starts)."""

    def __init__(self, setup: RunSetup, ray):
        self.setup, self.ray, self.cfg = setup, ray, setup.cfg.override({"progress": False})
        self.out = str(setup.out.resolve())  # absolute: a task resolves a relative path in its own folder
        self.remote = {f.__name__: ray.remote(f).options(num_cpus=TASK_CPUS, max_retries=TASK_RETRIES)
                       for f in (chunk_task, finish_task)}
        self.remote["prepare_task"] = ray.remote(prepare_task).options(num_cpus=TASK_CPUS, max_retries=TASK_RETRIES,
                                                                     num_returns=2)
        self.gt = ray.put(setup.gt)
        self.pending: dict = {}  # object ref -> (kind, class key)
        self.classes: dict[str, _Class] = {}
        self.tasks, self.retries, self.nodes, self.peak_mb = 0, 0, set(), 0.0
        resources = ray.cluster_resources()
        self.limit = int(resources.get("CPU", 1)) + 1
        self.store = STORE_SHARE * resources.get("object_store_memory", float("inf"))
        colls = setup.loaded.collections
        self.bar = tqdm(total=sum(len(c) for c in colls.values()), desc="objects", disable=not setup.cfg.progress)

    def _submit(self, name: str, kind: str, key: str, *args):
        refs = self.remote[name].remote(*args)
        self.tasks += 1
        ref = refs[1] if isinstance(refs, list) else refs
        self.pending[ref] = (kind, key)
        return refs

    def _start(self, key: str) -> None:
        coll = self.setup.loaded.collections[key]
        log.info(f"{key}: {len(coll)} objects")
        c = self.classes[key] = _Class(key, len(coll))
        report = ClassReport(key, objects=len(coll))
        done = finished_objects(coll, self.cfg, self.setup.out, report)
        c.plan, _ = self._submit("prepare_task", "prepare", key, self.ray.put(coll), self.cfg, self.gt,
                                 self.out, done, report)

    def run(self) -> dict:
        """Run every class; returns the executor's record for ``summary.json``."""
        queue = deque(sorted(self.setup.loaded.collections))
        while queue or self.pending:
            while queue and self._room(queue[0]):
                self._start(queue.popleft())
            ready, _ = self.ray.wait(list(self.pending), num_returns=1)
            kind, key = self.pending.pop(ready[0])
            try:
                value = self.ray.get(ready[0])
            except self.ray.exceptions.RayError as e:
                self._failed(key, e)
                continue
            getattr(self, f"_{kind}")(self.classes[key], value)
        self.bar.close()
        return {"name": "ray", "nodes": sorted(self.nodes), "tasks": self.tasks, "retries": self.retries,
                "peak_rss_task_mb": round(self.peak_mb, 1)}

    def _plan_bytes(self, key: str) -> float:
        return len(self.setup.loaded.collections[key]) * self.cfg.input.canvas_size ** 2 * PLAN_BYTES_PER_PIXEL

    def _room(self, key: str) -> bool:
        """Whether class ``key`` may start now."""
        if not self.classes:
            return True
        held = sum(self._plan_bytes(k) for k in self.classes)
        return len(self.classes) < self.limit and held + self._plan_bytes(key) <= self.store

    def _prepare(self, c: _Class, value) -> None:
        todo, c.report, ran = value
        self._ran(*ran)
        self.bar.update(c.objects - len(todo))
        if not todo:
            return self._book(c)
        n = self.cfg.ray_chunk_objects
        for c0 in range(0, len(todo), n):
            self._submit("chunk_task", "chunk", c.key, c.plan, todo[c0:c0 + n], self.cfg)
            c.left += 1

    def _chunk(self, c: _Class, value) -> None:
        part, puffballs, ran = value
        self._ran(*ran)
        self.bar.update(part.reconstructed + len(part.skipped))
        c.report.merge(part)
        c.puffballs.extend(puffballs)
        c.left -= 1
        self._chunks_back(c)

    def _chunks_back(self, c: _Class) -> None:
        if c.left > 0:
            return
        if c.error is not None:
            return self._book(c)
        self._submit("finish_task", "finish", c.key, c.plan, self.cfg, c.report, sorted(c.puffballs))

    def _finish(self, c: _Class, value) -> None:
        c.report, ran = value
        self._ran(*ran)
        self._book(c)

    def _ran(self, node: str, attempt: int | None, mb: float | None) -> None:
        """Book where a task ran, how often it had been tried before (``None``: this Ray does not say;
        the retries are then ``None``), and its process's peak memory."""
        self.nodes.add(node)
        self.retries = None if attempt is None or self.retries is None else self.retries + attempt
        self.peak_mb = max(self.peak_mb, mb or 0.0)

    def _failed(self, key: str, e: Exception) -> None:
        """A task of class ``key`` failed for good: the class is reported failed with the reason; its
        other chunks go on (their objects are kept)."""
        c = self.classes[key]
        if not isinstance(e, self.ray.exceptions.RayTaskError) and self.retries is not None:
            self.retries += TASK_RETRIES  # its worker or node died every time it was tried
        log.error(f"{key}: failed: {_reason(e)}")
        log.debug("".join(traceback.format_exception(e)))
        if c.error is None:
            c.error = _reason(e)
            if c.report is None:
                c.report = ClassReport(key, objects=c.objects)
            c.report.status = "failed"
            c.report.skip(c.error, "class")
        if c.left > 0:  # a chunk
            c.left -= 1
            return self._chunks_back(c)
        self._book(c)

    def _book(self, c: _Class) -> None:
        del self.classes[c.key]  # the plan's last ref goes: Ray frees it
        book_class(self.setup, c.key, c.report)


def run(cfg: Config, workers: int | None = None, threads: int | None = None) -> dict:
    """Run every class on Ray (:func:`connect` to ``cfg.ray_address``); write what
    :func:`carvi_torch.executors.local.run` writes, plus ``executor`` in ``summary.json``; return the summary.

    ``workers`` and ``threads`` are the local executor's and not used: a task writes its objects itself,
    on as many torch threads as it has CPUs. User errors (Ray not installed, a cluster that cannot be
    reached, a device other than the CPU) raise :class:`ConfigError` before anything is written.
    """
    ray = import_ray()
    if cfg.resolve_device().type != "cpu":
        raise ConfigError(f"executor=ray carves on the CPU; got device={cfg.device}")
    with log_to_terminal(quiet=not cfg.progress), connect(cfg.ray_address) as address:
        setup = open_run(cfg)
        with setup.lock, log_to_file(setup.out / "run.log"):
            announce(setup)
            log.info(f"Ray at {address}: {ray.cluster_resources().get('CPU', 0):g} CPUs")
            record = _Driver(setup, ray).run()
            setup.summary["executor"] = {"name": "ray", "address": address, **record}
            setup.summary["torch_threads"] = TASK_CPUS
            return finish_run(setup, 0)
