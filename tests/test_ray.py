"""executor=ray on a local two-node Ray cluster (1 CPU each, loopback only): the same files as the local
executor, resume across executors, the executor's record, and a worker killed during a run.

One module-scoped cluster serves every test (a Ray cluster takes seconds to start).
"""
from __future__ import annotations

import json
import os
import platform
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from carvi_torch.config import Config, ConfigError
from carvi_torch.executors import run

ROOT = Path(__file__).resolve().parents[1]
TINY = {"procedural_instances": 6, "resolution": 20, "proposals": 4, "canvas_size": 64, "progress": False,
        "refine_iters": 30, "plane_size": 32, "preview": False, "keep_all_scores": True,
        "classes": ["bottle", "car"]}  # a rotationally symmetric class and a bilateral one


def _cfg(out, **extra) -> Config:
    return Config().override({**TINY, "out": str(out), **extra})


def _ray():
    return pytest.importorskip("ray", reason="Ray is not installed (pip install 'carvi_torch[ray]')")


@pytest.fixture(scope="module")
def local_started(tmp_path_factory, procedural_input):
    """The reference, the local executor's run of the tiny collection, started in a process of its own
    (it computes while the cluster below starts, which mostly waits)."""
    _ray()
    out = tmp_path_factory.mktemp("local")
    procedural_input(out)  # the embedded collection, generated once per session, where the run looks for it
    config, err = out.parent / "local.yaml", out.parent / "local.err"
    config.write_text(_cfg(out).to_yaml())
    with open(err, "w") as f:
        proc = subprocess.Popen([sys.executable, "-m", "carvi_torch.reconstruct", "--config", str(config)], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=f)
    yield out, proc, err
    proc.kill()


@pytest.fixture(scope="module")
def cluster(local_started):
    """A head node that runs no task (0 CPUs: it holds the driver and Ray's services) and two worker
    nodes of 1 CPU each, on 127.0.0.1, started in a working folder of their own (not the tests'); this
    process connected to it. Yields it and the worker nodes."""
    ray = _ray()
    from ray.cluster_utils import Cluster

    from carvi_torch.executors.ray import loopback

    tmp = tempfile.mkdtemp(prefix="cr-")  # short: Ray's socket paths must fit 107 bytes
    with loopback(), pytest.MonkeyPatch.context() as mp:
        mp.setenv("RAY_TMPDIR", tmp)
        mp.setenv("RAY_USAGE_STATS_ENABLED", "0")
        here = os.getcwd()
        os.chdir(tmp)  # Ray's processes work there; the tests, back where they were
        c = Cluster(initialize_head=True, head_node_args=dict(num_cpus=0, include_dashboard=False,
                                                              node_ip_address="127.0.0.1"))
        try:
            nodes = [c.add_node(num_cpus=1, node_ip_address="127.0.0.1") for _ in range(2)]
            ray.init(address=c.address, log_to_driver=False)
            os.chdir(here)
            yield c, nodes
        finally:
            os.chdir(here)
            ray.shutdown()
            c.shutdown()
            shutil.rmtree(tmp, ignore_errors=True)


@pytest.fixture(scope="module")
def local(local_started):
    """The reference run's folder and summary."""
    out, proc, err = local_started
    assert proc.wait(timeout=600) == 0, err.read_text()[-2000:]
    return out, json.loads((out / "summary.json").read_text())


def _files(root: Path) -> dict[str, bytes]:
    """Every file a run wrote for its classes, by path (cameras.json, voxels, meshes, scores), but the
    hidden temporary files of atomic writes that a killed process may leave (never read)."""
    return {str(p.relative_to(root)): p.read_bytes() for cls in TINY["classes"]
            for p in sorted((root / cls).rglob("*"))
            if p.is_file() and not (p.name.startswith(".") and p.name.endswith(".tmp"))}


def _same_files(a: Path, b: Path) -> None:
    fa, fb = _files(a), _files(b)
    assert fa.keys() == fb.keys() and len(fa) > 10
    different = [k for k in fa if fa[k] != fb[k]]
    assert not different, different


def _counts(summary: dict) -> dict:
    return {k: (c["status"], c["objects"], c["reconstructed"], c["resumed"], c["failures"])
            for k, c in summary["classes"].items()}


def test_ray_run_equals_local_run(cluster, local, tmp_path):
    """Same seed: byte-identical cameras.json, voxels, meshes and proposal scores, the same reports; the
    executor's record names the worker nodes that ran the tasks (both: two classes start at once), and
    counts every task: per class one viewpoint task, one per chunk of 2 objects, one closing task."""
    c, nodes = cluster
    out, ref = local
    got = run(_cfg(tmp_path, data=ref["data"], executor="ray", ray_address=c.address, ray_chunk_objects=2))
    _same_files(out, tmp_path)
    from carvi_torch.config import object_settings
    from carvi_torch.io.layout import file_settings

    made = [file_settings(p) for p in sorted((tmp_path / "car" / "voxels").glob("*.npz"))]
    assert len(made) == 6 and all(m == object_settings(_cfg(tmp_path)) for m in made)  # the tasks' writers too
    assert _counts(got) == _counts(ref)
    assert all(v["reconstructed"] == 6 for v in got["classes"].values())
    ex = got["executor"]
    assert ex["name"] == "ray" and ex["address"] == c.address and ex["retries"] == 0
    assert ex["tasks"] == 2 * (1 + 3 + 1)
    assert sorted(ex["nodes"]) == sorted(n.node_id for n in nodes)
    assert ref["executor"] == {"name": "local", "address": None, "nodes": [platform.node()], "tasks": 2, "retries": 0}


def test_resume_across_executors(cluster, local, tmp_path):
    """A local run's folder with some objects lost, and one whose voxels file holds no input fingerprint (an
    older run's): a Ray run redoes just those (the same files again), says so (``redone``), and its summary
    keeps the class it did not run (merged); a local rerun into that folder then resumes all."""
    c, _ = cluster
    out, ref = local
    shutil.copytree(out, tmp_path, dirs_exist_ok=True)
    meshes = sorted((tmp_path / "car" / "meshes").glob("*.ply"))
    lost = meshes[:3]
    for p in lost:
        p.unlink()
    older = tmp_path / "car" / "voxels" / f"{meshes[3].stem}.npz"
    with np.load(older) as z:
        members = {k: z[k] for k in z.files if k != "input_fingerprint"}
    np.savez(older, **members)
    got = run(_cfg(tmp_path, data=ref["data"], executor="ray", ray_address=c.address, classes=["car"]))
    car = got["classes"]["car"]
    assert (car["reconstructed"], car["resumed"]) == (len(lost) + 1, 6 - len(lost) - 1)
    assert car["redone"] == {"count": 1, "no_input_record": [int(meshes[3].stem)]}
    assert got["classes"]["bottle"] == ref["classes"]["bottle"] and got["classes_from_earlier_runs"] == ["bottle"]
    _same_files(out, tmp_path)
    again = run(_cfg(tmp_path, data=ref["data"], classes=["car"]), workers=0)["classes"]["car"]  # resumes: inline
    assert (again["resumed"], again["reconstructed"]) == (6, 0)


def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _kill_a_chunk_task(raylets: list[int], stop: threading.Event, killed: list) -> None:
    """Kill (SIGKILL) the first worker process of ``raylets`` seen running a chunk task."""
    while not stop.is_set() and not killed:
        for pid in (w for r in raylets for w in _children(r)):
            try:
                title = Path(f"/proc/{pid}/cmdline").read_bytes()
            except OSError:
                continue
            if title.startswith(b"ray::chunk_task"):
                os.kill(pid, signal.SIGKILL)
                killed.append(pid)
                return
        time.sleep(0.01)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds Ray's worker processes in /proc")
def test_a_killed_worker_is_retried(cluster, local, tmp_path):
    """A worker process killed while it carves a chunk: Ray runs the chunk again, the run finishes with
    every object (the same files as the local run), and the record counts the retry."""
    c, nodes = cluster
    out, ref = local
    raylets = [n.all_processes["raylet"][0].process.pid for n in nodes]
    stop, killed = threading.Event(), []
    killer = threading.Thread(target=_kill_a_chunk_task, args=(raylets, stop, killed), daemon=True)
    killer.start()
    try:
        got = run(_cfg(tmp_path, data=ref["data"], executor="ray", ray_address=c.address, ray_chunk_objects=6))
    finally:
        stop.set()
        killer.join()
    assert killed, "no chunk task was seen running"
    assert got["executor"]["retries"] >= 1
    assert all(v["status"] == "ok" and v["reconstructed"] == 6 for v in got["classes"].values())
    _same_files(out, tmp_path)


def test_without_ray_one_line(monkeypatch, tmp_path):
    """executor=ray where Ray is not installed: a ConfigError saying how to install it, nothing written
    (runs with or without Ray installed)."""
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now raises ImportError
    with pytest.raises(ConfigError, match=r"pip install 'carvi_torch\[ray\]'"):
        run(_cfg(tmp_path / "out", executor="ray"))
    assert not (tmp_path / "out").exists()


def test_an_unreachable_head_is_one_line():
    """ray_address=host:port where nothing listens: a ConfigError at once (Ray itself would keep trying
    for minutes); ``auto`` is left to Ray."""
    from carvi_torch.executors.ray import check_reachable

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: refused
        with pytest.raises(ConfigError, match=f"ray_address=127.0.0.1:{port}: no Ray head answers there"):
            check_reachable(f"127.0.0.1:{port}")
        s.listen()
        check_reachable(f"127.0.0.1:{port}")
    check_reachable("auto")


def test_a_relative_out_is_the_drivers(cluster, local, tmp_path, monkeypatch):
    """--out relative to the driver's working folder: the tasks, whose processes work in another folder,
    write every object there too."""
    c, _ = cluster
    _, ref = local
    monkeypatch.chdir(tmp_path)
    got = run(_cfg("rel", data=ref["data"], executor="ray", ray_address=c.address, classes=["car"]))
    assert got["classes"]["car"]["reconstructed"] == 6
    assert len(list((tmp_path / "rel" / "car" / "meshes").glob("*.ply"))) == 6


def _start_alone(tmp_path: Path, data: str, env: dict, **extra) -> subprocess.Popen:
    """``carvi_torch.reconstruct`` with executor=ray for the car class, started in a process of its own (this
    one holds a Ray connection), with ``env`` over a copy of this environment without the loopback switch;
    its output goes to ``tmp_path/out``, its stderr to ``tmp_path/stderr``."""
    from carvi_torch.executors.ray import LOOPBACK_VAR

    config = tmp_path / "run.yaml"
    config.write_text(_cfg(tmp_path / "out", data=data, executor="ray", classes=["car"], **extra).to_yaml())
    env = {**{k: v for k, v in os.environ.items() if k != LOOPBACK_VAR}, **env}
    with open(tmp_path / "stderr", "w") as err:
        return subprocess.Popen([sys.executable, "-m", "carvi_torch.reconstruct", "--config", str(config)], cwd=ROOT,
                                env=env, stdout=subprocess.DEVNULL, stderr=err)


@pytest.fixture(scope="module")
def runs_alone(cluster, local, tmp_path_factory):
    """The two runs in processes of their own, started at once (each mostly waits for Ray and torch to start):
    ``own`` with ray_address unset, with a fresh home folder (``own/home``) and RAY_ADDRESS naming a cluster that
    does not answer; ``loopback`` with ray_address the cluster's 127.0.0.1:PORT. The carving kernel's cache stays
    this process's (``CARVI_TORCH_CACHE``): a fresh home would have the run compile the kernel again. Yields a
    function that waits for a run: ``(folder, exit status, stderr)``."""
    from carvi_torch.carve import native

    c, _ = cluster
    _, ref = local
    own, loop = tmp_path_factory.mktemp("own"), tmp_path_factory.mktemp("loopback")
    (own / "home").mkdir()
    procs = {"own": (own, _start_alone(own, ref["data"], {"HOME": str(own / "home"), "RAY_ADDRESS": "127.0.0.1:1",
                                                          "CARVI_TORCH_CACHE": str(native.library_path().parents[1])})),
             "loopback": (loop, _start_alone(loop, ref["data"], {}, ray_address=c.address))}

    def wait(name):
        folder, proc = procs[name]
        return folder, proc.wait(timeout=300), (folder / "stderr").read_text()

    yield wait
    for _, proc in procs.values():
        proc.kill()
        proc.wait()


def test_a_ray_of_its_own_ignores_ray_address_and_home(runs_alone):
    """ray_address unset: the run starts a Ray of its own, even where RAY_ADDRESS names a cluster (here
    one that does not answer), without token authentication: no ``~/.ray`` (a token file) in the home
    folder, no warning about tokens."""
    folder, status, stderr = runs_alone("own")
    assert status == 0, stderr[-2000:]
    assert len(list((folder / "out" / "car" / "meshes").glob("*.ply"))) == 6
    home = folder / "home"
    assert not [p for p in home.rglob("*") if ".ray" in p.parts or "ray" in p.name]
    assert "token" not in stderr.lower()


def test_a_loopback_address_connects_over_loopback(runs_alone):
    """ray_address=127.0.0.1:PORT from a process without the loopback switch: the run connects over
    loopback and finishes."""
    folder, status, stderr = runs_alone("loopback")
    assert status == 0, stderr[-2000:]
    assert len(list((folder / "out" / "car" / "meshes").glob("*.ply"))) == 6


def test_environ_sets_removes_and_restores(monkeypatch):
    """The environment of the connect: variables set, removed, and restored afterwards."""
    from carvi_torch.executors.ray import environ, is_loopback

    monkeypatch.setenv("RAY_ADDRESS", "127.0.0.1:1")
    monkeypatch.delenv("RAY_AUTH_MODE", raising=False)
    with environ(RAY_AUTH_MODE="disabled", RAY_ADDRESS=None):
        assert os.environ["RAY_AUTH_MODE"] == "disabled" and "RAY_ADDRESS" not in os.environ
    assert os.environ["RAY_ADDRESS"] == "127.0.0.1:1" and "RAY_AUTH_MODE" not in os.environ
    assert [is_loopback(a) for a in ("127.0.0.1:6379", "localhost:1", "[::1]:2", "10.0.0.5:6379", "auto")] == \
        [True, True, True, False, False]


def test_a_head_that_is_not_ray_is_a_bounded_wait(monkeypatch):
    """ray_address where something other than Ray listens: Ray is imported (and so configured) with one try
    of GCS_WAIT_S seconds (its default is 20 tries of 35 s), a setting the user made is kept, the environment is
    restored after, and the failure is a ConfigError naming the address."""
    import types

    from carvi_torch.executors import ray as ray_executor

    seen = {}

    def init(address=None, **kw):
        raise ConnectionError(f"Failed to connect to Ray cluster at {address}")

    def import_ray():  # Ray reads the settings when it is imported
        seen.update({k: os.environ.get(k) for k in ("RAY_py_gcs_connect_timeout_s", "RAY_gcs_server_port_wait_time_s")})
        return types.SimpleNamespace(is_initialized=lambda: False, init=init, shutdown=lambda: None)

    monkeypatch.setattr(ray_executor, "import_ray", import_ray)
    monkeypatch.delenv("RAY_py_gcs_connect_timeout_s", raising=False)
    monkeypatch.setenv("RAY_gcs_server_port_wait_time_s", "7")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        address = f"127.0.0.1:{s.getsockname()[1]}"
        with pytest.raises(ConfigError, match=f"ray_address={address}: cannot start or reach Ray"):
            with ray_executor.connect(address):
                pass
    assert seen == {"RAY_py_gcs_connect_timeout_s": str(ray_executor.GCS_WAIT_S),
                    "RAY_gcs_server_port_wait_time_s": "7"}
    assert "RAY_py_gcs_connect_timeout_s" not in os.environ and os.environ["RAY_gcs_server_port_wait_time_s"] == "7"
