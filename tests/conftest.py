"""Shared test fixtures.

Tests that read the real data in ``../shared/data`` (relative to the project root)
take the ``shared_data`` fixture: they are skipped, with the reason, when a
checkout has no such folder (a user's clone).

``OMP_WAIT_POLICY=PASSIVE`` (unless set): the suite runs processes side by side (writer processes, Ray
nodes, child processes) on few cores, where OpenMP threads that spin after each parallel region take the
cores the other threads and processes need (the test files that compute most ran 5 to 7 times slower that
way on a loaded 2-core machine). Set here, before torch loads its OpenMP runtime; the child processes
inherit it. Only the waiting changes: thread counts and results are the same.

Ctrl-C is made to raise again where the suite was started with SIGINT ignored (``nohup``, or ``make test &``
from a script: a background job inherits the ignored signal, and so would every child process the tests
interrupt, which then rightly keeps ignoring it); the tests of interrupts need the default behaviour.
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import signal  # noqa: E402

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:  # a Python handler: child processes start with the default
    signal.signal(signal.SIGINT, signal.default_int_handler)

import copy  # noqa: E402
import functools  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = (ROOT / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (../shared/data beside the checkout); "
                    "these tests need the PASCAL3D+ CAD models and PASCAL VOC aeroplanes")
    return SHARED_DATA


def record_settings(paths, **changed) -> None:
    """Rewrite the voxels files at ``paths`` as if their objects had been made with the settings ``changed``
    (dotted keys with ``.`` as ``__``: ``carve__resolution=16``) besides those they record."""
    import numpy as np

    from carvi_torch.io.layout import SETTINGS_MEMBER, file_settings, settings_text

    for path in paths:
        made = {**file_settings(path), **{k.replace("__", "."): v for k, v in changed.items()}}
        with np.load(path) as z:
            members = {k: z[k] for k in z.files}
        np.savez(path, **{**members, SETTINGS_MEMBER: np.asarray(settings_text(made))})


def load_tool(name: str, as_name: str | None = None):
    """``tools/<name>.py`` loaded as a module (registered in ``sys.modules`` under ``as_name``, default
    ``name``, so that its dataclasses find their module)."""
    as_name = as_name or name
    spec = importlib.util.spec_from_file_location(as_name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[as_name] = module
    spec.loader.exec_module(module)
    return module


@functools.lru_cache(maxsize=None)
def _read_cad_models(directory: str) -> tuple:
    from carvi_torch.synthetic import load_models

    return tuple(load_models(directory))


def cad_models(shared_data: Path, prefix: str = "") -> list:
    """The PASCAL3D+ CAD models named ``prefix*``, as ``load_models`` reads them (left/right names of the
    class). The folder is read once per session (all 73 models, over a second each time); every call gets
    deep copies, so that nothing one test does to a model reaches another."""
    return [copy.deepcopy(m) for m in _read_cad_models(str(shared_data / "pascal3d_cad")) if m.name.startswith(prefix)]


def render_cad_class(shared_data: Path, out: Path, prefix: str, views: int, seed: int = 0):
    """The PASCAL3D+ CAD models named ``prefix*`` rendered ``views`` times each into ``out``:
    ``(collection, true rotations (n, 3, 3) float64, models)``."""
    import json

    from carvi_torch.io.coco import load_coco
    from carvi_torch.synthetic.render import render_dataset

    models = cad_models(shared_data, prefix)
    render_dataset(models, out, views=views, seed=seed, progress=False)
    coll = load_coco(out / "annotations.json").collections[prefix]
    gt = json.loads((out / "gt.json").read_text())["annotations"]
    R = torch.tensor([gt[str(a)]["R"] for a in coll.annotation_ids], dtype=torch.float64)
    return coll, R, models


#: The fork server of :func:`run_each_in_a_fresh_process`: a process that imported torch and nothing of the
#: package, and forks a child per code it is sent (one request per stdin line: JSON ``{"codes", "argv",
#: "env", "cwd"}``), the children of a request at once; it answers one line, ``[[exit status, stdout,
#: stderr], ...]`` as JSON. torch starts no thread on import and imports neither ``resource`` nor anything of
#: the package, so a child is a fresh process for the package; torch's import (seconds per process) is paid
#: once per session.
_ZYGOTE = r"""
import json, os, sys, tempfile, traceback
import torch  # noqa: F401
assert not [m for m in sys.modules if m.split(".")[0] == "carvi_torch"] and "resource" not in sys.modules
requests, reply = sys.stdin, sys.stdout


def child(code, argv, env, cwd, out, err):
    os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
    for fd, path in ((1, out), (2, err)):
        os.dup2(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), fd)
    try:
        if env is not None:
            os.environ.clear()
            os.environ.update(env)
        if cwd is not None:
            os.chdir(cwd)
        sys.argv = argv
        exec(compile(code, "<child>", "exec"), {"__name__": "__main__"})
        status = 0
    except SystemExit as e:
        status = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, (int, type(None))):
            print(e.code, file=sys.stderr)
    except BaseException:
        traceback.print_exc()
        status = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


for line in requests:
    req = json.loads(line)
    tmp, pids = tempfile.mkdtemp(), []
    files = [(os.path.join(tmp, f"{i}.out"), os.path.join(tmp, f"{i}.err")) for i in range(len(req["codes"]))]
    for code, (out, err) in zip(req["codes"], files):
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            child(code, req["argv"], req["env"], req["cwd"], out, err)
        pids.append(pid)
    res = []
    for pid, paths in zip(pids, files):
        status = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
        res.append([status] + [open(p, errors="replace").read() for p in paths])
        for p in paths:
            os.unlink(p)
    os.rmdir(tmp)
    reply.write(json.dumps(res) + "\n")
    reply.flush()
"""
_zygote: dict = {}


def _zygote_process():
    """The fork server, started on first use (stopped at the end of the session: :func:`pytest_sessionfinish`)."""
    import subprocess

    proc = _zygote.get("proc")
    if proc is None or proc.poll() is not None:
        paths = [str(ROOT), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)]
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}  # no empty entry: the cwd stays off the path
        proc = subprocess.Popen([sys.executable, "-c", _ZYGOTE], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                text=True, env=env)
        _zygote.update(proc=proc)
    return proc, proc.stdin


def pytest_sessionfinish(session, exitstatus):
    proc = _zygote.pop("proc", None)
    if proc is not None:
        proc.stdin.close()  # the server's loop ends
        try:
            proc.wait(timeout=30)
        except Exception:  # noqa: BLE001
            proc.kill()


def run_each_in_a_fresh_process(codes: list[str], argv: list[str] | None = None, env: dict | None = None,
                                cwd=None, timeout: float = 600) -> list[tuple[int, str, str]]:
    """Each Python source of ``codes`` run as ``__main__`` in a process of its own, all at once, as ``python -c
    CODE *argv`` would run it with environment ``env`` (default: this one's) in ``cwd``: ``(exit status,
    stdout, stderr)`` per code. Where the system forks, the processes are forked from a server that imported
    torch alone (``_ZYGOTE``); the package's folder is on their path, as ``PYTHONPATH`` puts it."""
    import select
    import subprocess

    argv = ["-c", *(argv or [])]
    if not hasattr(os, "fork"):
        env = {**(os.environ if env is None else env), "PYTHONPATH": str(ROOT)}
        procs = [subprocess.Popen([sys.executable, "-c", c, *argv[1:]], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=env, cwd=cwd) for c in codes]
        outs = [p.communicate(timeout=timeout) for p in procs]
        return [(p.returncode, *o) for p, o in zip(procs, outs)]
    proc, requests = _zygote_process()
    env = dict(os.environ if env is None else env)  # as subprocess: the caller's environment of now
    requests.write(json.dumps({"codes": codes, "argv": argv, "env": env,
                               "cwd": None if cwd is None else str(cwd)}) + "\n")
    requests.flush()
    ready, _, _ = select.select([proc.stdout], [], [], timeout)
    if not ready:
        proc.kill()
        raise TimeoutError(f"the fork server's children did not finish within {timeout} s")
    line = proc.stdout.readline()
    assert line, "the fork server died"
    return [tuple(r) for r in json.loads(line)]


#: Objects per class of the embedded procedural collection that the end-to-end tests run on.
PROCEDURAL_INSTANCES = 6


@pytest.fixture(scope="session")
def procedural_input(tmp_path_factory):
    """The embedded procedural collection (``PROCEDURAL_INSTANCES`` per class, the default seed), generated
    once per session as ``reconstruct`` generates it; a function that copies it to ``out/input``, where a
    run of ``out`` without ``--data`` finds it complete and takes it instead of generating it again."""
    import shutil

    from carvi_torch.config import Config
    from carvi_torch.synthetic import procedural

    src = tmp_path_factory.mktemp("procedural") / "input"
    procedural.default_collection(src, PROCEDURAL_INSTANCES, Config().seed)

    def copy_to(out: Path) -> Path:
        shutil.copytree(src, Path(out) / "input")
        return Path(out) / "input" / "annotations.json"

    return copy_to


#: The settings of :func:`pipeline_run`: every stage at a tiny size.
PIPELINE_TINY = {"procedural_instances": 6, "resolution": 20, "proposals": 4, "canvas_size": 64, "progress": False,
        "refine_iters": 30, "plane_size": 32, "preview": True, "report": False, "keep_all_scores": True}


@pytest.fixture(scope="session")
def pipeline_run(tmp_path_factory, procedural_input):
    """A run of every class of the embedded collection with ``PIPELINE_TINY`` (without ``--data``: it takes the
    collection from ``out/input``), once per session: ``(out, summary)``. Tests read it; test_pipeline.py's
    reruns into it resume every object and change none of its outputs."""
    from carvi_torch.config import Config
    from carvi_torch.executors import run

    out = tmp_path_factory.mktemp("run")
    assert PIPELINE_TINY["procedural_instances"] == PROCEDURAL_INSTANCES
    procedural_input(out)
    summary = run(Config().override({**PIPELINE_TINY, "out": str(out)}))
    return out, summary


@pytest.fixture
def generator() -> torch.Generator:
    """A seeded CPU generator, so every test is deterministic."""
    return torch.Generator().manual_seed(0)


def cuda_available() -> bool:
    return torch.cuda.is_available()


#: Marks a test as needing CUDA: ``pytest -m cuda`` selects every such test (a session with a
#: GPU runs them all with ``tools/gpu_session.sh``); without a device they are skipped by
#: :func:`pytest_collection_modifyitems`.
requires_cuda = pytest.mark.cuda


#: The test files that take longest (``pytest --durations``, summed per file: 20-60 s each on the 2-core host),
#: longest first. :func:`pytest_collection_modifyitems` puts them first, so that ``make test``'s processes
#: (``--dist loadfile --no-loadscope-reorder``: whole files, in this order) end together instead of one of
#: them running the last long file alone.
LONGEST_FIRST = ("test_tools", "test_ray", "test_sfm_mixture", "test_pipelined_classes", "test_evaluate",
                 "test_robustness", "test_export", "test_carve_native", "test_pipeline", "test_metrics")


def _file_rank(item) -> int:
    stem = item.path.stem
    return LONGEST_FIRST.index(stem) if stem in LONGEST_FIRST else len(LONGEST_FIRST)


def pytest_collection_modifyitems(config, items):
    """The longest test files first (:data:`LONGEST_FIRST`; a stable sort: the tests of a file keep their order);
    skip the tests marked ``cuda`` when no CUDA device is present, with the reason."""
    items.sort(key=_file_rank)
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (CI has none)")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)
