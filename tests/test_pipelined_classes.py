"""Pipelined classes (``pipeline_classes``, ``viewpoint_processes``, :mod:`carvi_torch.executors.ahead`): the next
classes' viewpoints made on a background thread or in worker processes while this class carves give the sequential
run's files; a class whose viewpoints fail there fails alone, with the sequential run's reason; an interrupt does
not wait for the thread, and the run resumes."""
from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import carvi_torch.carve.chunks as chunks_module
import carvi_torch.executors.local as L
import carvi_torch.pipeline as P
from carvi_torch.config import Config
from carvi_torch.executors import run
from conftest import PIPELINE_TINY

#: Two classes of the embedded collection (6 objects each), written inline.
CLASSES = ["car", "chair"]
#: The mixture of shapes at a tiny size (as in test_pipeline's shape-group run): car splits into 2 groups.
GROUPS = {"sfm_groups": 2, "sfm_group_min": 2, "sfm_group_misfit": 0, "sfm_group_hull_gain": -1, "sfm_max_outer": 40,
          "sfm_group_rounds": 2}
#: What differs between two runs of the same objects: timings, memory, where the input lies.
UNTIMED = {"seconds", "total_seconds", "load_seconds", "peak_rss_mb", "peak_rss_workers_mb", "data", "gt"}


def _cfg(out: Path, data: Path, **extra) -> Config:
    return Config().override({**PIPELINE_TINY, "out": str(out), "data": str(data), "classes": CLASSES,
                              "preview": False, **extra})


def _untimed(x):
    if isinstance(x, dict):
        return {k: _untimed(v) for k, v in x.items() if k not in UNTIMED}
    return [_untimed(v) for v in x] if isinstance(x, list) else x


def _assert_same_outputs(a: Path, b: Path) -> int:
    """Every file of the class folders the same (cameras.json and meshes byte for byte, every array of the
    ``.npz`` files), and ``summary.json`` with its classes in the same order, timings aside; returns the files."""
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    assert list(sa["classes"]) == list(sb["classes"]) == CLASSES
    assert _untimed(sa) == _untimed(sb)
    files = sorted(p.relative_to(a) for c in CLASSES for p in (a / c).rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(b) for c in CLASSES for p in (b / c).rglob("*") if p.is_file())
    for rel in files:
        if rel.suffix == ".npz":
            x, y = np.load(a / rel), np.load(b / rel)
            assert x.files == y.files and all(np.array_equal(x[k], y[k]) for k in x.files), rel
        else:
            assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    return len(files)


@pytest.fixture(scope="module")
def sequential(procedural_input, tmp_path_factory):
    """The sequential runs (``pipeline_classes=False``) that the tests compare with, each made once per settings:
    ``sequential(**extra)`` gives ``(out, summary, the classes whose viewpoints went through
    executors.local.class_viewpoints)``; the tests' runs go there, the sequential run makes them in
    pipeline.prepare_class."""
    runs = {}

    def get(**extra):
        key = json.dumps(extra, sort_keys=True)
        if key not in runs:
            out = tmp_path_factory.mktemp("sequential")
            data, seen, make = procedural_input(out), [], L.class_viewpoints

            def viewpoints(coll, *args, **kwargs):
                seen.append(coll.meta.key)
                return make(coll, *args, **kwargs)

            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(L, "class_viewpoints", viewpoints)
                summary = run(_cfg(out / "run", data, pipeline_classes=False, **extra), workers=0)
            runs[key] = (out / "run", summary, seen)
        return runs[key]

    return get


@pytest.mark.parametrize("extra", [{}, GROUPS], ids=["one_shape", "mixture"])
def test_pipelined_classes_give_the_sequential_files(procedural_input, tmp_path, monkeypatch, extra, sequential):
    """The chair's viewpoints are made on the background thread while the car carves (the car's carving waits
    until they have started, so the overlap is certain), and every file is the sequential run's."""
    data = procedural_input(tmp_path)
    started, threads, counts = threading.Event(), {}, {}
    make, carve = L.class_viewpoints, P._carve_chunks

    def viewpoints(coll, *args, **kwargs):
        threads[coll.meta.key] = threading.current_thread().name
        counts[coll.meta.key] = torch.get_num_threads()
        if coll.meta.key == CLASSES[1]:
            started.set()
        return make(coll, *args, **kwargs)

    def carve_waiting(plan, *args, **kwargs):
        if plan.coll.meta.key == CLASSES[0]:
            assert started.wait(60), "the next class's viewpoints did not start while this class carved"
        return carve(plan, *args, **kwargs)

    monkeypatch.setattr(L, "class_viewpoints", viewpoints)
    monkeypatch.setattr(P, "_carve_chunks", carve_waiting)
    piped = run(_cfg(tmp_path / "piped", data, **extra), workers=0)
    monkeypatch.setattr(P, "_carve_chunks", carve)
    assert set(threads) == set(CLASSES) and threading.main_thread().name not in threads.values()
    assert set(counts.values()) == {piped["torch_threads"]}  # the thread runs the run's intra-op count
    seq_out, seq, seen = sequential(**extra)
    assert seen == []  # the sequential run made its viewpoints in pipeline.prepare_class, on its thread
    assert all(piped["classes"][c]["reconstructed"] == seq["classes"][c]["reconstructed"] == 6 for c in CLASSES)
    if extra:
        assert piped["classes"]["car"]["sfm_groups"]["groups"] == 2  # the mixture's paths ran
    assert _assert_same_outputs(tmp_path / "piped", seq_out) >= 2 * (1 + 6 + 6)


def test_a_class_whose_viewpoints_fail_ahead_fails_alone(procedural_input, tmp_path, monkeypatch):
    """The car's viewpoints raise on the background thread: the car is failed with the one-line reason the
    sequential run gives, the chair is reconstructed, the summary keeps class order."""
    data = procedural_input(tmp_path)
    where = []

    def failing(make):
        def viewpoints(coll, *args, **kwargs):
            if coll.meta.key == "car":
                where.append(threading.current_thread().name)
                raise RuntimeError("simulated failure of the car's viewpoints")
            return make(coll, *args, **kwargs)
        return viewpoints

    monkeypatch.setattr(L, "class_viewpoints", failing(L.class_viewpoints))
    piped = run(_cfg(tmp_path / "piped", data), workers=0)
    monkeypatch.setattr(P, "class_viewpoints", failing(P.class_viewpoints))
    sequential = run(_cfg(tmp_path / "sequential", data, pipeline_classes=False, stage="cameras"), workers=0)
    assert where[0] != threading.main_thread().name and where[1] == threading.main_thread().name
    assert list(piped["classes"]) == CLASSES
    car = piped["classes"]["car"]
    assert car["status"] == "failed" and car["failures"] == [
        {"annotation_id": None, "source": None, "stage": "class",
         "reason": "RuntimeError: simulated failure of the car's viewpoints"}]
    assert _untimed(car) == _untimed(sequential["classes"]["car"])
    assert piped["classes"]["chair"]["status"] == "ok" and piped["classes"]["chair"]["reconstructed"] == 6


def test_an_interrupt_does_not_wait_for_the_thread_and_the_run_resumes(procedural_input, tmp_path, monkeypatch):
    """Ctrl-C while the car carves its second chunk (its first 4 objects written) and the chair's viewpoints are
    still being made: ``run`` returns at once (it does not join the thread: here it would wait for ever), the
    thread, once done, has written nothing of the chair, and a rerun resumes the car's 4 objects and
    reconstructs the rest."""
    data = procedural_input(tmp_path)
    release, returned, chunks = threading.Event(), threading.Event(), []
    make, carve = L.class_viewpoints, P.carve_and_select
    assert chunks_module.CPU_CHUNK_OBJECTS == 4  # the car's 6 objects are carved in two chunks

    def slow_viewpoints(coll, *args, **kwargs):
        if coll.meta.key == "chair":
            release.wait(120)
            returned.set()
        return make(coll, *args, **kwargs)

    def interrupted(ids, plan, *args, **kwargs):
        chunks.append(plan.coll.meta.key)
        if len(chunks) == 2:
            raise KeyboardInterrupt
        return carve(ids, plan, *args, **kwargs)

    monkeypatch.setattr(L, "class_viewpoints", slow_viewpoints)
    monkeypatch.setattr(P, "carve_and_select", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(_cfg(tmp_path, data), workers=0)
    assert chunks == ["car", "car"] and not returned.is_set()  # run() came back while the chair's were on their way
    release.set()
    assert returned.wait(120)
    assert not (tmp_path / "chair").exists()  # the thread writes nothing
    monkeypatch.setattr(P, "carve_and_select", carve)
    again = run(_cfg(tmp_path, data), workers=0)["classes"]
    assert [(again[c]["status"], again[c]["resumed"], again[c]["reconstructed"]) for c in CLASSES] == [
        ("ok", 4, 2), ("ok", 0, 6)]


def test_viewpoint_processes_give_the_sequential_files(procedural_input, tmp_path, monkeypatch, sequential):
    """``viewpoint_processes=2``: both classes' viewpoint stages (the car's mixture of shapes included) are made in
    worker processes and handed to the run (``made``), and every file is the sequential run's."""
    data = procedural_input(tmp_path)
    made, make = {}, L.class_viewpoints

    def viewpoints(coll, *args, made_here=made, **kwargs):
        made_here[coll.meta.key] = kwargs.get("made")
        return make(coll, *args, **kwargs)

    monkeypatch.setattr(L, "class_viewpoints", viewpoints)
    procs = run(_cfg(tmp_path / "procs", data, viewpoint_processes=2, **GROUPS), workers=0)
    assert set(made) == set(CLASSES) and all(m is not None and m[0] is not None for m in made.values())
    assert procs["classes"]["car"]["sfm_groups"]["groups"] == 2 and "sfm" in procs["classes"]["car"]["seconds"]
    assert _assert_same_outputs(tmp_path / "procs", sequential(**GROUPS)[0]) >= 2 * (1 + 6 + 6)


def test_viewpoint_processes_that_fail_leave_the_class_here_or_fail_it_alone(procedural_input, tmp_path,
                                                                              monkeypatch, sequential):
    """A worker process that died (``BrokenProcessPool``) leaves the car's viewpoints to the run, which logs it and
    gives the sequential cameras; an error raised in a worker fails the chair alone with its one-line reason."""
    from concurrent.futures import Future
    from concurrent.futures.process import BrokenProcessPool

    from carvi_torch.executors import ahead

    data = procedural_input(tmp_path)

    def submit(self, coll, cfg, gt=None):
        future = Future()
        future.set_exception(BrokenProcessPool("killed") if coll.meta.key == "car" else RuntimeError("chair broke"))
        return future

    monkeypatch.setattr(ahead.AheadProcesses, "submit", submit)
    procs = run(_cfg(tmp_path / "procs", data, viewpoint_processes=2, stage="cameras"), workers=0)
    assert (tmp_path / "procs" / "car" / "cameras.json").read_bytes() == (
        sequential(stage="cameras")[0] / "car" / "cameras.json").read_bytes()
    assert "car: the viewpoint process stopped (killed)" in (tmp_path / "procs" / "run.log").read_text()
    chair = procs["classes"]["chair"]
    assert chair["status"] == "failed" and [f["reason"] for f in chair["failures"]] == ["RuntimeError: chair broke"]
    assert not (tmp_path / "procs" / "chair").exists()


def test_a_broken_viewpoint_pool_leaves_the_classes_to_the_run(procedural_input, tmp_path, monkeypatch, sequential):
    """A worker process dies before the first class is handed over: the pool is broken for good (every submission
    raises), both classes' viewpoints are made in the run's process, with the sequential cameras, and it says so."""
    import os
    from concurrent.futures.process import BrokenProcessPool

    from carvi_torch.executors import ahead

    data = procedural_input(tmp_path)
    real, broken = ahead.AheadProcesses.submit, []

    def breaking(self, coll, cfg, gt=None):
        if not broken:
            with pytest.raises(BrokenProcessPool):
                self._pool.submit(os._exit, 1).result(timeout=120)
            broken.append(coll.meta.key)
        return real(self, coll, cfg, gt)

    monkeypatch.setattr(ahead.AheadProcesses, "submit", breaking)
    procs = run(_cfg(tmp_path / "procs", data, viewpoint_processes=2, stage="cameras"), workers=0)
    assert broken == ["car"] and [procs["classes"][c]["status"] for c in CLASSES] == ["cameras", "cameras"]
    for c in CLASSES:
        assert (tmp_path / "procs" / c / "cameras.json").read_bytes() == (
            sequential(stage="cameras")[0] / c / "cameras.json").read_bytes()
        log_text = (tmp_path / "procs" / "run.log").read_text()
        assert f"{c}: no viewpoint process can take it (BrokenProcessPool" in log_text


def test_an_interrupt_stops_the_viewpoint_processes(procedural_input, tmp_path, monkeypatch):
    """Ctrl-C while the car carves: the worker processes are stopped (SIGTERM), not left to finish their classes
    (which the interpreter's exit would wait for), and nothing of the chair is written."""
    import multiprocessing
    import signal

    from carvi_torch.executors import ahead

    data = procedural_input(tmp_path)
    made = []
    monkeypatch.setattr(L, "AheadProcesses", lambda *a: made.append(ahead.AheadProcesses(*a)) or made[-1])

    before = {p.pid for p in multiprocessing.active_children()}

    def interrupted(*args, **kwargs):
        processes = [p for p in multiprocessing.active_children() if p.pid not in before]  # the submissions' workers
        made.append(processes)
        raise KeyboardInterrupt

    monkeypatch.setattr(P, "_carve_chunks", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run(_cfg(tmp_path, data, viewpoint_processes=2), workers=0)
    processes = made[1]
    assert processes
    for p in processes:
        p.join(60)
        for _ in range(600):  # the pool's own thread may reap the process first and set its code a moment later
            if p.exitcode is not None:
                break
            time.sleep(0.1)
        assert p.exitcode == -signal.SIGTERM  # an idle worker told to shut down would exit with 0
    assert not (tmp_path / "chair").exists()


#: A run interrupted while the background thread is inside torch operations (``sys.argv[1]``: out).
INTERRUPTED_RUN = """
import sys, time, torch
import carvi_torch.executors.local as L, carvi_torch.pipeline as P
from carvi_torch.config import Config
from carvi_torch.executors import run
def busy(coll, *args, **kwargs):  # the chair's viewpoints: torch work still running when the run leaves
    if coll.meta.key == "chair":
        end, x = time.monotonic() + 1.5, torch.randn(300, 300)
        while time.monotonic() < end:
            x = torch.tanh(x @ x.T / 300)
    return make(coll, *args, **kwargs)
def interrupted(*args, **kwargs):
    raise KeyboardInterrupt
make, L.class_viewpoints, P._carve_chunks = L.class_viewpoints, busy, interrupted
cfg = Config().override({"out": sys.argv[1], "procedural_instances": 6, "canvas_size": 64, "resolution": 20,
                         "proposals": 4, "progress": False, "preview": False, "report": False,
                         "classes": ["car", "chair"]})
try:
    run(cfg, workers=0)
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(130)
"""


def test_an_interrupted_process_exits_with_its_status(tmp_path):
    """The process exits with the interrupt's status (130) once the background thread's operations end,
    instead of being aborted by the interpreter stopping that thread inside torch at exit."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", INTERRUPTED_RUN, str(tmp_path / "out")], capture_output=True,
                          text=True, timeout=300)
    assert done.returncode == 130, done.stderr[-2000:]
    assert done.stdout.strip() == "interrupted" and "terminate called" not in done.stderr


def _tensors(x, seen=None):
    """Every tensor reachable from ``x``: through dataclass and object attributes, lists, tuples and dicts."""
    seen = set() if seen is None else seen
    if id(x) in seen or isinstance(x, (str, bytes, int, float, bool, type(None))):
        return []
    seen.add(id(x))
    if isinstance(x, torch.Tensor):
        return [x]
    if isinstance(x, dict):
        return [t for v in x.values() for t in _tensors(v, seen)]
    if isinstance(x, (list, tuple, set)):
        return [t for v in x for t in _tensors(v, seen)]
    return [t for v in getattr(x, "__dict__", {}).values() for t in _tensors(v, seen)]


@pytest.mark.parametrize("extra", [{}, GROUPS], ids=["one_shape", "mixture"])
def test_viewpoints_on_the_cpu_reach_the_run_device_whole(procedural_input, tmp_path, monkeypatch, extra):
    """``viewpoints.device=cpu``: the stage runs on the CPU, and every tensor of its result (cameras, shape groups
    and their SfMs, distance maps) and of the class reaches the run's device before the surrogate plan, but the
    canonical frame's, which stay on the host as in every run. ``meta`` stands in for a second device (a CUDA
    one in a CUDA run; the CUDA test compares the outputs)."""
    from carvi_torch.io.coco import load_coco

    cfg = _cfg(tmp_path, procedural_input(tmp_path), **{f"viewpoints.{k}": v for k, v in extra.items()},
               **{"viewpoints.device": "cpu"})
    coll = load_coco(cfg.data, canvas_size=cfg.input.canvas_size, classes=["car"]).collections["car"]
    handed = {}

    def plan(coll, vp, *a):
        handed.update(coll=coll, vp=vp)
        return "plan"

    monkeypatch.setattr(P, "_surrogate_plan", plan)
    seen_devices = []
    estimate = P.estimate_viewpoints
    monkeypatch.setattr(P, "estimate_viewpoints", lambda c, *a, **k: seen_devices.append(c.masks.device) or
                        estimate(c, *a, **k))
    coll_out, vp, got, _ = P.class_viewpoints(coll, cfg, torch.device("meta"), torch.Generator().manual_seed(0))
    assert got == "plan" and seen_devices == [torch.device("cpu")]
    assert handed["vp"] is vp and handed["coll"] is coll_out
    assert extra == {} or vp.groups.k == 2  # the mixture's split, with its per-group SfMs, moved too
    # the canonical frame stays on the host, where every run makes it and cameras.json reads it
    frame = {id(t) for t in _tensors(vp.frame)}
    assert frame and {t.device.type for t in _tensors(vp.frame)} == {"cpu"}
    found = [t for t in _tensors(vp) + _tensors(coll_out) if id(t) not in frame]
    assert len(found) > 30 and {t.device.type for t in found} == {"meta"}


def test_viewpoints_handed_over_make_the_same_class_files(procedural_input, tmp_path):
    """The hand-over path of ``viewpoints.device=cpu`` end to end up to carving, on the host: ``cpu:0`` names the
    same memory as ``cpu`` but another device, so the result is handed over (``Viewpoints.to``) and the class's
    ``cameras.json``, its selection reference and its carving maps come out as on the direct path."""
    from carvi_torch.io.coco import load_coco

    data = procedural_input(tmp_path)
    plans = {}
    for name, device, extra in (("direct", torch.device("cpu"), {}),
                                ("handed", torch.device("cpu", 0), {"viewpoints.device": "cpu"})):
        cfg = _cfg(tmp_path / name, data, **extra)
        coll = load_coco(cfg.data, canvas_size=cfg.input.canvas_size, classes=["car"]).collections["car"]
        plans[name], todo, _ = P.prepare_class(coll, cfg, device, torch.Generator().manual_seed(0), out=tmp_path / name)
        assert todo
    a, b = (json.loads((tmp_path / n / "car" / "cameras.json").read_text()) for n in ("direct", "handed"))
    assert a == b
    pa, pb = plans["direct"], plans["handed"]
    assert torch.equal(pa.selection.averages, pb.selection.averages)
    assert torch.equal(pa.maps.ext, pb.maps.ext) and torch.equal(pa.maps.entry_map, pb.maps.entry_map)
    assert torch.equal(pa.object_from_camera, pb.object_from_camera)


def test_to_device_keeps_containers_and_sharing():
    """``runtime.to_device`` (what ``Viewpoints.to`` builds on): a dict subclass stays that subclass (a default
    dict keeps its factory), a named tuple its type, an object reached twice is moved once and stays shared,
    and non-tensors are left as they are."""
    from collections import OrderedDict, defaultdict, namedtuple

    from carvi_torch.runtime import to_device

    Pair = namedtuple("Pair", "a b")
    shared = torch.ones(3)
    dd = defaultdict(list, {"x": shared})
    obj = {"od": OrderedDict([("b", torch.zeros(1)), ("a", 2)]), "dd": dd, "pair": Pair(shared, "s"), "again": shared}
    moved = to_device(obj, "meta")
    assert type(moved) is dict and type(moved["od"]) is OrderedDict and list(moved["od"]) == ["b", "a"]
    assert type(moved["dd"]) is defaultdict and moved["dd"].default_factory is list and moved["dd"] is not dd
    assert moved["dd"]["missing"] == [] and "missing" not in dd  # the copy, not the original, grew
    assert type(moved["pair"]) is Pair and moved["pair"].b == "s" and moved["od"]["a"] == 2
    assert moved["again"] is moved["pair"].a is moved["dd"]["x"] and moved["again"].device.type == "meta"
    assert shared.device.type == "cpu" and obj["od"]["b"].device.type == "cpu"  # the originals stay
