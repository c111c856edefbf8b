"""Shared test fixtures.

Tests that read the real data in ``../shared/data`` (relative to the project root)
take the ``shared_data`` fixture: they are skipped, with the reason, when a
checkout has no such folder (a user's clone).
"""
from __future__ import annotations

import importlib.util
import json
import os
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = (ROOT / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Path of ``../shared/data``; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA} (../shared/data beside the checkout); "
                    "these tests need the PASCAL3D+ CAD models and PASCAL VOC aeroplanes")
    return SHARED_DATA


def load_tool(name: str, as_name: str | None = None):
    """``tools/<name>.py`` loaded as a module (registered in ``sys.modules`` under ``as_name``, default
    ``name``, so that its dataclasses find their module)."""
    as_name = as_name or name
    spec = importlib.util.spec_from_file_location(as_name, ROOT / "tools" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[as_name] = module
    spec.loader.exec_module(module)
    return module


def render_cad_class(shared_data: Path, out: Path, prefix: str, views: int, seed: int = 0):
    """The PASCAL3D+ CAD models named ``prefix*`` rendered ``views`` times each into ``out``:
    ``(collection, true rotations (n, 3, 3) float64, models)``."""
    import json

    from carvi_torch.io.coco import load_coco
    from carvi_torch.synthetic import load_models
    from carvi_torch.synthetic.render import render_dataset

    models = [m for m in load_models(shared_data / "pascal3d_cad") if m.name.startswith(prefix)]
    render_dataset(models, out, views=views, seed=seed, progress=False)
    coll = load_coco(out / "annotations.json").collections[prefix]
    gt = json.loads((out / "gt.json").read_text())["annotations"]
    R = torch.tensor([gt[str(a)]["R"] for a in coll.annotation_ids], dtype=torch.float64)
    return coll, R, models


#: Runs each code of ``argv[1:]`` in a child forked from a process that imported torch and nothing of the
#: package, the children at once; prints ``[[exit status, stdout, stderr], ...]`` as JSON. torch starts no
#: thread on import and imports neither ``resource`` nor anything of the package, so a child is a fresh
#: process for the package; torch's import (seconds per process) is paid once.
_FORK_EACH = r"""
import json, os, sys, tempfile, traceback
import torch  # noqa: F401
assert not [m for m in sys.modules if m.split(".")[0] == "carvi_torch"] and "resource" not in sys.modules
tmp, pids = tempfile.mkdtemp(), []
sys.stdout.flush()
for i, code in enumerate(sys.argv[1:]):
    pid = os.fork()
    if pid == 0:
        for fd, name in ((1, "out"), (2, "err")):
            os.dup2(os.open(os.path.join(tmp, f"{i}.{name}"), os.O_WRONLY | os.O_CREAT, 0o600), fd)
        try:
            exec(compile(code, "<child>", "exec"), {"__name__": "__main__"})
            status = 0
        except SystemExit as e:
            status = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            if not isinstance(e.code, (int, type(None))):
                print(e.code, file=sys.stderr)
        except BaseException:
            traceback.print_exc()
            status = 1
        sys.stdout.flush(); sys.stderr.flush()
        os._exit(status)
    pids.append(pid)
res = []
for i, pid in enumerate(pids):
    status = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
    res.append([status] + [open(os.path.join(tmp, f"{i}.{n}")).read() for n in ("out", "err")])
    for n in ("out", "err"):
        os.unlink(os.path.join(tmp, f"{i}.{n}"))
os.rmdir(tmp)
print(json.dumps(res))
"""


def run_each_in_a_fresh_process(codes: list[str], **kwargs) -> list[tuple[int, str, str]]:
    """Each Python source of ``codes`` run as ``__main__`` in a process of its own, all at once (``kwargs``:
    ``cwd``, ``env`` of ``subprocess.run``): ``(exit status, stdout, stderr)`` per code. Where the system
    forks, the processes are forked from one that imported torch alone (see ``_FORK_EACH``)."""
    import subprocess

    if not hasattr(os, "fork"):
        procs = [subprocess.Popen([sys.executable, "-c", c], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  text=True, **kwargs) for c in codes]
        outs = [p.communicate(timeout=300) for p in procs]
        return [(p.returncode, *o) for p, o in zip(procs, outs)]
    proc = subprocess.run([sys.executable, "-c", _FORK_EACH, *codes], capture_output=True, text=True, timeout=300,
                          **kwargs)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return [tuple(r) for r in json.loads(proc.stdout.strip().splitlines()[-1])]


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


def pytest_collection_modifyitems(config, items):
    """Skip the tests marked ``cuda`` when no CUDA device is present, with the reason."""
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device (CI has none)")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)
