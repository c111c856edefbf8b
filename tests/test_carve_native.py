"""Tests of the native carving kernel (``carvi_torch.carve.native``, ``kernels/carve_native.cpp``).

References: ``grid_sample`` (samples bit for bit), the torch carving and the per-proposal loop (labels
voxel for voxel, on random blobs, steep maps and the real PASCAL VOC aeroplanes), a count of the samples
dense carving reads. The loader's checks are tested white-box (its private build and check functions). The cache's
rules (private directory, owner, mode and SHA-256 of a library checked before it is loaded, atomic and
concurrent builds) and the fallbacks without a compiler run in child processes with their own caches
(forked from one that imported torch alone, so each is fresh for the package: conftest's fork server):
a library that fails a check must be rebuilt, never loaded (a truncated one could kill the process). The
children's compiler is a shim that copies a library built here, whatever ``$CXX`` is (see ``compiler_shim``);
the real compiles are this process's own (on a fresh cache) and the portable build's.
"""
from __future__ import annotations

import hashlib
import importlib
import json
import os
import shlex
import shutil
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from carvi_torch.cameras import ScaledOrthographic, random_rotations
from carvi_torch.carve import carve_proposals, carve_proposals_loop, prepare_maps
from carvi_torch.carve.torch_backend import grid_sample_maps, kernel_inputs
from carvi_torch.config import Config, ConfigError
from carvi_torch.sdf import signed_distance
from conftest import run_each_in_a_fresh_process
from test_carve import blob_masks, random_cameras, random_proposals

MODULE = "carvi_torch.carve.native"
native = importlib.import_module(MODULE)
native_library = importlib.import_module("carvi_torch.native_library")
ROOT = Path(sys.modules["carvi_torch"].__file__).resolve().parents[1]

needs_kernel = pytest.mark.skipif(not native.available(), reason=f"kernel unavailable: {native.unavailable_reason()}")


def _problem(seed: int, n: int, M: int = 8, B: int = 12, V: int = 4, size: int = 32, steep: bool = False):
    """Random blob silhouettes and cameras: ``(maps, reference, views, (ext, slots, scale, G, column_cost))``."""
    gen = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                            indexing="ij")
    centre = size / 3 + size / 3 * torch.rand(M, 2, generator=gen)
    radius = size / 8 + size / 8 * torch.rand(M, 2, generator=gen)
    sdf = torch.sqrt(((xx - centre[:, 0, None, None]) / radius[:, 0, None, None]) ** 2
                     + ((yy - centre[:, 1, None, None]) / radius[:, 1, None, None]) ** 2) * 5 - 5
    if steep:
        sdf = sdf + 4.0 * torch.randn(sdf.shape, generator=gen)
    cams = ScaledOrthographic(random_rotations(M, generator=gen).float(), 1 + 0.2 * torch.rand(M, generator=gen),
                              centre.clone())
    maps = prepare_maps(sdf, cams)
    reference = torch.randint(0, M, (B,), generator=gen)
    views = torch.stack([(reference + 1 + torch.randint(0, M - 1, (B,), generator=gen)) % M for _ in range(V)], 1)
    views[::3, -1] = -1  # unused slots
    return maps, reference, views, kernel_inputs(maps, reference, views, n)[:5]


# --------------------------------------------------------------------------- samples and labels


def test_available_says_why_not():
    assert isinstance(native.available(), bool)
    assert (native.unavailable_reason() is None) == native.available()
    assert native.variant() in ({"fma", "plain"} if native.available() else {None})


@needs_kernel
@pytest.mark.parametrize("size", [(2, 2), (5, 9), (64, 48), (161, 143)])
def test_sample_equals_grid_sample_bit_for_bit(size):
    gen = torch.Generator().manual_seed(sum(size))
    ext = torch.randn(3, *size, generator=gen) * 30
    ext[2] = torch.randn(size, generator=gen) * 1e6
    grid = torch.rand(50000, 2, generator=gen) * 2.6 - 1.3
    grid[:2000] = torch.round(grid[:2000] * 16) / 16
    for k in range(3):
        for scale in (1.0, 0.37, 2.9):
            want = grid_sample_maps((ext[k] * scale)[None, None], grid.view(1, 1, -1, 2)).view(-1)
            assert torch.equal(native.sample(ext, k, scale, grid), want)


@needs_kernel
@pytest.mark.parametrize("imprint, n, steep", [(True, 14, False), (False, 14, False), (True, 9, True),
                                               (True, 23, False), (False, 17, True)])
def test_labels_equal_the_torch_carving(imprint, n, steep):
    maps, reference, views, inputs = _problem(6 + n, n, steep=steep)
    want = carve_proposals(maps, None, reference, views, resolution=n, imprint=imprint,
                                               backend="torch")
    occ, columns, nonempty, samples = native.carve_labels(*inputs, n, imprint)
    B = len(reference)
    assert occ.dtype == columns.dtype == nonempty.dtype == torch.bool and samples.dtype == torch.int64
    assert occ.shape == (B, n, n * n) and columns.shape == (B, n * n) and nonempty.shape == (B,)
    assert torch.equal(occ.view(B, n, n, n), want.occupancy) and torch.equal(~nonempty, want.empty)
    assert torch.equal(columns.view(B, n, n), want.columns)
    assert want.occupancy.any()


@needs_kernel
@pytest.mark.parametrize("threads", [1, 2])
def test_threads_do_not_change_the_labels(threads):
    n = 15
    maps, reference, views, inputs = _problem(11, n, B=13)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = native.carve_labels(*inputs, n, True)
        torch.set_num_threads(threads)
        many = native.carve_labels(*inputs, n, True)
    finally:
        torch.set_num_threads(before)
    for a, b in zip(one, many):
        assert torch.equal(a, b)
    want = carve_proposals(maps, None, reference, views, resolution=n, backend="torch")
    assert torch.equal(many[0].view(want.occupancy.shape), want.occupancy)


@needs_kernel
def test_the_last_map_is_read_safely_and_non_contiguous_inputs_are_copied():
    n = 14
    _, _, _, (ext, slots, scale, G, cc) = _problem(8, n)
    last = ext.shape[0] - 1
    slots = torch.where(slots >= 0, torch.full_like(slots, last), slots)
    ext = ext.clone()
    ext[last] = ext[0]
    a = native.carve_labels(ext, slots, scale, G, cc, n, True)
    b = native.carve_labels(torch.cat([ext, torch.zeros_like(ext[:1])]), slots, scale, G, cc, n, True)
    c = native.carve_labels(ext, slots.t().contiguous().t(), scale, G, cc, n, True)  # transposed twice: strided
    for x, y, z in zip(a, b, c):
        assert torch.equal(x, y) and torch.equal(x, z)


@needs_kernel
def test_the_other_variant_carves_too():
    n = 12
    _, _, _, inputs = _problem(21, n)
    other = "plain" if native.variant() == "fma" else "fma"
    if other == "fma" and not native.operators().has_fma():
        pytest.skip("no AVX2/FMA here")
    chosen, alt = native.carve_labels(*inputs, n, True), native.carve_labels(*inputs, n, True, variant=other)
    assert torch.equal(chosen[1], alt[1]) and torch.equal(chosen[2], alt[2])
    with pytest.raises(ValueError, match="variant"):
        native.carve_labels(*inputs, n, True, variant="avx512")


@needs_kernel
def test_the_portable_build_carves_like_the_x86_one(tmp_path, monkeypatch):
    """The code for processors without AVX2 (``CARVI_NO_X86``: what aarch64 compiles, and MSVC) builds,
    gives the plain variant's labels, and refuses the fma variant instead of running AVX2 code. Built with
    ``-O0`` instead of ``-O3`` (the same float arithmetic: ``-ffp-contract=off``, no fast math), which halves
    the compile; the optimised build is the one every other test runs."""
    assert native_library._FLAGS[0] == "-O3"
    monkeypatch.setattr(native_library, "_FLAGS", ["-O0", *native_library._FLAGS[1:]])
    d = native_library._private_dir(tmp_path / "kernels")
    namespace = f"carvi_portable_{native_library._key()}"  # its own namespace: safe beside the x86 one
    path = d / f"{namespace}.so"
    with native_library._dir_lock(d, exclusive=True):
        native_library._build(path, namespace, ("-DCARVI_NO_X86",))
    assert native.cache_entry_problem(path) is None
    torch.ops.load_library(str(path))
    ops = getattr(torch.ops, namespace)
    assert ops.has_fma() is False
    n = 13
    inputs = _problem(14, n)[3]
    want = native.carve_labels(*inputs, n, True, variant="plain")
    for x, y in zip(want, ops.carve_labels(*inputs, n, True, False)):
        assert torch.equal(x, y)
    with pytest.raises(ValueError, match="needs a processor with AVX2 and FMA"):
        ops.carve_labels(*inputs, n, True, True)


# --------------------------------------------------------------------------- input checks at the operator


@needs_kernel
def test_every_input_is_checked():
    n = 10
    ext, slots, scale, G, cc = _problem(9, n)[3]
    B = slots.shape[0]
    cases = [
        (TypeError, "views must be Long", (ext, slots.float(), scale, G, cc, n)),
        (TypeError, "ext must be Float", (ext.double(), slots, scale, G, cc, n)),
        (TypeError, "G must be Float", (ext, slots, scale, G.half(), cc, n)),
        (ValueError, "CPU tensors; ext", (ext.to("meta"), slots, scale, G, cc, n)),
        (ValueError, "CPU tensors; views", (ext, slots.to("meta"), scale, G, cc, n)),
        (ValueError, "ext must have 3 dimensions", (ext[0], slots, scale, G, cc, n)),
        (ValueError, "scale, G, column_cost", (ext, slots, scale, G, cc[:, :-1], n)),
        (ValueError, "scale, G, column_cost", (ext, slots, scale[:-1], G, cc, n)),
        (ValueError, "scale, G, column_cost", (ext, slots, scale, G[..., :3], cc, n)),
        (ValueError, "views must index", (ext, torch.full_like(slots, ext.shape[0]), scale, G, cc, n)),
        (ValueError, "views must index", (ext, torch.full_like(slots, -2), scale, G, cc, n)),
        (ValueError, "at least one pixel", (ext[:, :0], slots, scale, G, cc, n)),
        (ValueError, "resolutions 1 to 2048", (ext, slots, scale, G, cc, 0)),
        (ValueError, "resolutions 1 to 2048", (ext, slots, scale, G, cc, 2049)),
        (ValueError, "at most 64 view slots",
         (ext, torch.full((B, 65), -1), torch.ones(B, 65), torch.zeros(B, 65, 2, 4), cc, n)),
    ]
    for exc, match, args in cases:
        with pytest.raises(exc, match=match):
            native.carve_labels(*args, True)


@needs_kernel
def test_the_operators_check_what_the_wrapper_would_fix():
    """Called directly (no Python wrapper), the operators refuse what they cannot read safely."""
    ops = native.operators()
    ext, slots, scale, G, cc = _problem(9, 10)[3]
    with pytest.raises(ValueError, match="views must be contiguous"):
        ops.carve_labels(ext, slots.t().contiguous().t(), scale, G, cc, 10, True, False)
    with pytest.raises(ValueError, match="map 5 of"):
        ops.sample(ext[:5], 5, 1.0, torch.zeros(3, 2), False)
    with pytest.raises(ValueError, match="grid must be"):
        ops.sample(ext, 0, 1.0, torch.zeros(3, 3), False)
    with pytest.raises(ValueError, match="a line has 1 to 2048"):
        ops.line(ext, 0, 1.0, 0.1, 0.1, 0.0, 0.0, 0, False)
    with pytest.raises(ValueError, match="map -1 of"):
        ops.line(ext, -1, 1.0, 0.1, 0.1, 0.0, 0.0, 5, False)


# --------------------------------------------------------------------------- the cache, in child processes


_CHILD = """
import json, os, sys, importlib
native = importlib.import_module(sys.argv[1])
ok = native.available()
path = native.library_path()
print(json.dumps(dict(ok=ok, reason=native.unavailable_reason(), path=str(path),
                      rebuilt=native.status()["rebuilt"], mtime=path.stat().st_mtime_ns if path.exists() else None)))
"""


def _run_child(cache: Path, **env_extra) -> tuple[int, dict | None, str]:
    """``_CHILD`` in a fresh process (forked from one that imported torch alone) with ``cache`` as its cache."""
    env = dict(os.environ, CARVI_TORCH_CACHE=str(cache), PYTHONPATH=str(ROOT))
    env.update(env_extra)
    [(rc, out, err)] = run_each_in_a_fresh_process([_CHILD], argv=[MODULE], env=env)
    lines = out.strip().splitlines()
    return rc, (json.loads(lines[-1]) if rc == 0 and lines else None), err


_SHIM = """#!/bin/sh
# Stands in for the C++ compiler in the cache tests' child processes: it "builds" the kernel by copying a
# library built from the same sources, flags, compiler name and torch (so the same file name and operator
# namespace), after a pause as long as a build's first seconds.
echo "$*" >> "{log}"
out=""; prev=""
for a in "$@"; do [ "$prev" = "-o" ] && out="$a"; prev="$a"; done
[ -n "$out" ] || {{ echo "compiler shim: no -o" >&2; exit 1; }}
sleep "${{CARVI_SHIM_SECONDS:-0}}"
exec cp "{lib}" "$out"
"""


def _library_for_children(env: dict, folder: Path) -> Path:
    """The library a child with ``env`` (a ``CXX`` of its own) builds, compiled here by this process's compiler
    with that child's key and operator namespace."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("CXX", env["CXX"])
        key = native_library._key()
    lib = folder / f"carve_native-{key}.so"
    proc = subprocess.run(native_library._build_command(lib, f"carvi_{key}"), capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return lib


@pytest.fixture(scope="module")
def compiler_shim(tmp_path_factory) -> tuple[dict, Path]:
    """The environment (``PATH`` or ``CXX``) under which a child's build runs a shim that copies a library instead
    of compiling it, whatever ``$CXX`` is: the cache's rules, lock, atomic replace and checks all run as in a
    real build, in a fraction of a compile's time. Also the log of the shim's invocations (one line per build).

    The key hashes the compiler's command line, so the children keep this process's: where ``$CXX`` (else
    ``c++``) starts with a command looked up on ``PATH``, the shim takes that command's name in a folder first
    on ``PATH`` and copies this process's library; where it starts with a path, the children's ``CXX`` is the
    shim itself and the library it copies is compiled once here for their key. A real compile is this process's
    own build (on a fresh cache), that one, and the portable build's test."""
    if not native.available():
        pytest.skip(f"kernel unavailable: {native.unavailable_reason()}")
    command = shlex.split(os.environ.get("CXX") or "c++")[0]
    d = tmp_path_factory.mktemp("shim")
    log = d / "builds.log"
    if os.sep in command:
        shim = d / "compiler-shim"
        env = {"CXX": str(shim)}
        lib = _library_for_children(env, d)
    else:
        shim = d / command
        env = {"PATH": f"{d}{os.pathsep}{os.environ.get('PATH', '')}"}
        lib = Path(native.status()["path"])
        assert lib.name == f"carve_native-{native_library._key()}.so"
    shim.write_text(_SHIM.format(log=log, lib=lib))
    os.chmod(shim, 0o755)
    return env, log


@pytest.fixture(scope="module")
def built_cache(tmp_path_factory, compiler_shim) -> tuple[Path, list]:
    """A cache built by two child processes started at once (the lock lets one build, the other wait and
    load); the tests that tamper with it work on copies. Also the children's reports. The build takes 1.5 s
    (the shim's pause), so the second child finds the first one building."""
    shim_env, log = compiler_shim
    before = log.read_text().count("\n") if log.exists() else 0
    cache = tmp_path_factory.mktemp("built")
    env = dict(os.environ, CARVI_TORCH_CACHE=str(cache), PYTHONPATH=str(ROOT), CARVI_SHIM_SECONDS="1.5", **shim_env)
    outs = run_each_in_a_fresh_process([_CHILD, _CHILD], argv=[MODULE], env=env)  # two processes at once
    assert all(rc == 0 for rc, _out, _err in outs), [err[-2000:] for _rc, _out, err in outs]
    assert log.read_text().count("\n") == before + 1  # one build: the compiler ran once
    return cache, [json.loads(out.strip().splitlines()[-1]) for _rc, out, _err in outs]


def _copy_cache(src: Path, dst: Path) -> Path:
    """``dst`` holding a copy of ``src``'s kernels (modes kept); the library's path in it."""
    shutil.copytree(src / "kernels", dst / "kernels")
    lib = [p for p in (dst / "kernels").iterdir() if p.suffix == ".so"]
    assert len(lib) == 1
    return lib[0]


def _assert_rebuilt(cache: Path, lib: Path, tampered: bytes | None, why: str, env: dict) -> None:
    """A child process (environment ``env`` added) finds the library rejected for ``why``, rebuilds it (no
    crash) and uses it."""
    rc, res, err = _run_child(cache, **env)
    assert rc == 0, f"child died ({rc}): {err[-2000:]}"
    assert res["ok"] and res["path"] == str(lib), res
    assert res["rebuilt"] is not None and why in res["rebuilt"], res
    assert tampered is None or lib.read_bytes() != tampered
    assert (lib.parent / (lib.name + ".sha256")).read_text().strip() == hashlib.sha256(lib.read_bytes()).hexdigest()
    assert not stat.S_IMODE(lib.stat().st_mode) & 0o022
    assert not [p for p in lib.parent.iterdir() if p.name.startswith(".build-")]


@needs_kernel
def test_a_fresh_cache_is_private_and_the_library_is_reused(tmp_path, built_cache, compiler_shim):
    built_cache, _ = built_cache
    shim_env, _log = compiler_shim  # the children's compiler, so that they look for the library built with it
    kernels = built_cache / "kernels"
    assert stat.S_IMODE(kernels.stat().st_mode) == 0o700
    lib = [p for p in kernels.iterdir() if p.suffix == ".so"][0]
    assert not stat.S_IMODE(lib.stat().st_mode) & 0o077
    assert (kernels / (lib.name + ".sha256")).read_text().strip() == hashlib.sha256(lib.read_bytes()).hexdigest()
    copy = _copy_cache(built_cache, tmp_path)
    mtime = copy.stat().st_mtime_ns
    rc, res, err = _run_child(tmp_path, **shim_env)
    assert rc == 0 and res["ok"] and res["rebuilt"] is None and res["mtime"] == mtime, (res, err)
    os.chmod(tmp_path / "kernels", 0o777)  # a cache directory of ours opened up: closed again
    rc, res, err = _run_child(tmp_path, **shim_env)
    assert rc == 0 and res["ok"] and stat.S_IMODE((tmp_path / "kernels").stat().st_mode) == 0o700, err


def _planted_library(tmp_path: Path, marker: Path) -> bytes:
    """A shared library that, when loaded, writes ``marker`` (built with ``cc``; the test skips without it)."""
    src = tmp_path / "planted.c"
    src.write_text(textwrap.dedent(f"""
        #include <stdio.h>
        __attribute__((constructor)) static void planted(void) {{
            FILE *f = fopen("{marker}", "w"); if (f) {{ fputs("loaded", f); fclose(f); }}
        }}
    """))
    out = tmp_path / "planted.so"
    try:
        subprocess.run(["cc", "-shared", "-fPIC", "-o", str(out), str(src)], check=True, capture_output=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"no C compiler to build the planted library: {exc}")
    return out.read_bytes()


@needs_kernel
def test_a_planted_library_is_rebuilt_not_loaded(tmp_path, built_cache, compiler_shim):
    """A library of another owner, mode 0777, with a matching hash beside it: rebuilt, its constructor never runs."""
    marker = tmp_path / "marker"
    planted = _planted_library(tmp_path, marker)
    cache = tmp_path / "cache"
    lib = _copy_cache(built_cache[0], cache)
    lib.write_bytes(planted)  # with a matching sidecar: only the owner or the mode gives it away
    (lib.parent / (lib.name + ".sha256")).write_text(hashlib.sha256(planted).hexdigest() + "\n")
    os.chmod(lib, 0o777)
    why = "writable by others"
    if os.getuid() == 0:
        os.chown(lib, 12345, 12345)
        why = "belongs to uid 12345"
    shim_env, log = compiler_shim
    before = log.read_text().count("\n")
    _assert_rebuilt(cache, lib, planted, why, shim_env)
    assert log.read_text().count("\n") == before + 1  # the rebuild ran the compiler
    assert not marker.exists(), "the planted library was loaded"


@needs_kernel
@pytest.mark.parametrize("damage", ["truncated", "wrong hash", "missing hash", "sidecar mode 0666"])
def test_a_damaged_cache_entry_is_refused_before_it_is_mapped(tmp_path, built_cache, damage):
    """Each damage is named by the check that runs before any load (a dlopen of a truncated library could
    SIGBUS); the rebuild that follows a refusal is the planted library's test."""
    lib = _copy_cache(built_cache[0], tmp_path)
    sidecar = lib.parent / (lib.name + ".sha256")
    assert native.cache_entry_problem(lib) is None
    if damage == "truncated":
        lib.write_bytes(lib.read_bytes()[: lib.stat().st_size // 2])
        why = "SHA-256"
    elif damage == "wrong hash":
        sidecar.write_text("0" * 64 + "\n")
        why = "SHA-256"
    elif damage == "missing hash":
        sidecar.unlink()
        why = "missing"
    else:
        os.chmod(sidecar, 0o666)
        why = "writable by others"
    problem = native.cache_entry_problem(lib)
    assert problem is not None and why in problem, problem


@needs_kernel
def test_a_cache_directory_of_another_user_is_not_used(tmp_path):
    if os.getuid() != 0:
        pytest.skip("changing a directory's owner needs root")
    (tmp_path / "kernels").mkdir(mode=0o700)
    os.chown(tmp_path / "kernels", 12345, 12345)
    rc, res, err = _run_child(tmp_path)
    assert rc == 0 and res["ok"] is False and "belongs to uid 12345" in res["reason"], (res, err)


@needs_kernel
def test_two_processes_building_at_once(built_cache):
    cache, res = built_cache
    assert all(r["ok"] for r in res) and sum(r["rebuilt"] is not None for r in res) == 1, res
    files = sorted(p.name for p in (cache / "kernels").iterdir())
    lib = Path(res[0]["path"])
    assert files == sorted([".lock", lib.name, lib.name + ".sha256"]), files
    assert (lib.parent / (lib.name + ".sha256")).read_text().strip() == hashlib.sha256(lib.read_bytes()).hexdigest()


def test_the_cache_lock_is_shared_to_load_and_exclusive_to_build(tmp_path, monkeypatch):
    """The cache directory's lock (``.lock``, private): checks and loads share it, a build holds it alone; a lock
    file this process cannot open for writing is locked read-only; where the platform has no ``flock`` nothing is
    locked and the build goes on."""
    import errno
    import threading

    from carvi_torch import runtime
    from carvi_torch.runtime import FileLock

    def attempt(exclusive: bool) -> bool:
        """Whether another holder could take the lock now, ``exclusive`` or shared."""
        with FileLock(tmp_path / ".lock") as other:
            try:
                return other.lock(exclusive, wait=False)
            except BlockingIOError:
                return False
    with native_library._dir_lock(tmp_path, exclusive=False), native_library._dir_lock(tmp_path, exclusive=False):
        assert attempt(exclusive=False) and not attempt(exclusive=True)
    assert not stat.S_IMODE((tmp_path / ".lock").stat().st_mode) & 0o077
    real_open = os.open

    def no_write(path, flags, *mode):
        if str(path).endswith(".lock") and flags & os.O_RDWR:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, flags, *mode)
    with monkeypatch.context() as m:
        m.setattr(runtime.os, "open", no_write)
        with native_library._dir_lock(tmp_path, exclusive=True):
            assert not attempt(exclusive=False)
    assert attempt(exclusive=True)
    for code in (errno.ENOLCK, errno.EIO):  # a file system without locks: the build goes on unlocked; else raised
        def no_flock(fd, op, code=code):
            raise OSError(code, os.strerror(code))
        with monkeypatch.context() as m:
            m.setattr(runtime.fcntl, "flock", no_flock)
            if code == errno.EIO:
                with pytest.raises(OSError), native_library._dir_lock(tmp_path, exclusive=True):
                    pass
            else:
                ran = []
                with native_library._dir_lock(tmp_path, exclusive=True):
                    ran.append(True)
                assert ran
    with FileLock(tmp_path / ".lock") as held:
        held.lock()
        monkeypatch.setattr(runtime, "fcntl", None)

        def build_under_the_lock():
            with native_library._dir_lock(tmp_path, exclusive=True):
                pass
        build = threading.Thread(target=build_under_the_lock, daemon=True)
        build.start()
        build.join(timeout=30)
        assert not build.is_alive()  # it did not wait for the holder


@pytest.mark.parametrize("how", ["CXX=/nonexistent", "empty PATH"])
def test_without_a_compiler_the_kernel_is_unavailable_with_the_reason(tmp_path, how):
    extra = {"CXX": "/nonexistent/c++"} if how.startswith("CXX") else {"PATH": "", "CXX": ""}
    rc, res, err = _run_child(tmp_path, **extra)
    assert rc == 0, err
    assert res["ok"] is False and "compiler" in res["reason"], res
    assert ("/nonexistent/c++" if how.startswith("CXX") else "c++") in res["reason"]
    assert not list(tmp_path.rglob("*.so")) and not list(tmp_path.rglob(".build-*"))


# --------------------------------------------------------------------------- processes and threads


def _carve_in_forked_child(queue, args):
    torch.set_num_threads(1)
    queue.put([t.numpy().copy() for t in native.carve_labels(*args)])


@needs_kernel
def test_a_forked_child_carves_as_torch_operators_do():
    """No fork handling: the kernel runs in torch's own thread pool, so a forked child is in the state of
    every torch operator there. GNU OpenMP's threads do not survive a fork: after the parent ran a parallel
    region, a child that runs one (any torch operator on more than one thread: grid_sample as well as this
    kernel) waits forever; with ``torch.set_num_threads(1)`` (what torch's DataLoader workers do) it runs."""
    import multiprocessing as mp

    n = 12
    args = (*_problem(10, n)[3], n, True)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        want = native.carve_labels(*args)  # the parent's OpenMP threads now exist
    finally:
        torch.set_num_threads(before)
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_carve_in_forked_child, args=(queue, args))
    child.start()
    try:
        got = queue.get(timeout=120)
    finally:
        child.join(timeout=60)
        if child.exitcode is None:
            child.kill()
    assert child.exitcode == 0
    for x, y in zip(want, got):
        assert torch.equal(x, torch.from_numpy(y))


@needs_kernel
def test_loading_again_in_the_same_process_reuses_the_operators():
    """A second library defining the same operator namespace would abort the process: it is never loaded."""
    ops, path, rebuilt = native_library._open_library()
    assert ops is native.operators() or ops.carve_labels is native.operators().carve_labels
    assert rebuilt is None and path == native.library_path()


# --------------------------------------------------------------------------- through carve_proposals


@needs_kernel
def test_real_aeroplanes_fused_equals_torch(shared_data, tmp_path):
    """The pipeline's own proposals on the real PASCAL VOC aeroplanes: the same labels either way."""
    from carvi_torch import pipeline
    from carvi_torch.io import coco
    from carvi_torch.io.voc import convert

    ann = tmp_path / "aeroplane.json"
    convert(shared_data / "pascal_voc_aeroplane" / "keypoints", ann)
    # sfm_groups=1: the default fits a mixture of shapes to the aeroplanes and keeps one shape (misfit 0.063), so
    # the proposals, cameras and maps are those of the default, bit for bit, without the mixture's 6-7 s
    cfg = Config().override(dict(data=str(ann), progress=False, sfm_groups=1))
    loaded = coco.load_coco(ann, canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                            device=torch.device("cpu"),
                            classes=["aeroplane"])
    coll = loaded.collections["aeroplane"]
    gen = torch.Generator().manual_seed(cfg.seed)
    plan, todo, _ = pipeline.prepare_class(coll, cfg, torch.device("cpu"), gen)
    ref, views, valid = plan.proposals(torch.tensor(todo[:6]))
    ref, views = ref[valid], views[valid]
    assert len(ref) >= 20
    a = carve_proposals(plan.maps, None, ref, views, resolution=cfg.carve.resolution, backend="torch")
    b = carve_proposals(plan.maps, None, ref, views, resolution=cfg.carve.resolution, backend="fused")
    assert torch.equal(a.occupancy, b.occupancy) and torch.equal(a.columns, b.columns)
    assert torch.equal(a.empty, b.empty) and a.occupancy.any()


def test_backend_validation():
    sdf = signed_distance(blob_masks(2, 16, torch.Generator().manual_seed(0)))
    cams = random_cameras(2, 16, torch.Generator().manual_seed(0))
    args = (sdf, cams, torch.tensor([0]), torch.tensor([[1]]))
    with pytest.raises(ValueError, match="backend must be one of"):
        carve_proposals(*args, resolution=8, backend="cuda")
    for kw, why in ((dict(interpolation="nearest"), "bilinearly"), (dict(return_cost=True), "labels only")):
        with pytest.raises(ValueError, match=why):
            carve_proposals(*args, resolution=8, backend="fused", **kw)
        # auto falls back to torch for what the kernel does not do
        carve_proposals(*args, resolution=8, backend="auto", **kw)
    with pytest.raises(ConfigError, match="carve.backend"):
        Config().override(dict(carve_backend="gpu")).validate()


@needs_kernel
def test_fused_reads_fewer_samples_than_dense_carving():
    n = 20
    ext, slots, scale, G, column_cost = _problem(3, n, M=8, B=16, V=4, size=32)[3]
    occ, columns, nonempty, samples = native.carve_labels(ext, slots, scale, G, column_cost, n, imprint=False)
    fg = (column_cost < 0).sum(1)
    dense = fg * (slots >= 0).sum(1) * n  # what the torch backend samples: every view at every foreground voxel
    interior = occ.flatten(1).sum(1)
    used = (slots >= 0).sum(1)
    assert (samples <= dense).all() and samples.sum() < 0.9 * dense.sum()
    # an interior voxel needs every view; an exterior foreground voxel at least one (when there is a view)
    assert (samples >= interior * used + (fg * n - interior) * (used > 0)).all()
    assert torch.equal(nonempty, occ.flatten(1).any(1)) and torch.equal(columns, occ.any(1))


@needs_kernel
@pytest.mark.parametrize("imprint, n", [(True, 14), (False, 14), (True, 9), (True, 23)])
def test_fused_labels_equal_torch_and_loop_voxel_for_voxel(imprint, n):
    gen = torch.Generator().manual_seed(6 + n)
    sdf, cams, reference, views = random_proposals(gen, M=8, B=16, V=4, size=32)
    torch_out = carve_proposals(sdf, cams, reference, views, resolution=n, imprint=imprint, backend="torch")
    fused = carve_proposals(sdf, cams, reference, views, resolution=n, imprint=imprint, backend="fused")
    loop = carve_proposals_loop(sdf, cams, reference, views, resolution=n, imprint=imprint)
    for out in (torch_out, loop):
        assert torch.equal(fused.occupancy, out.occupancy)
        assert torch.equal(fused.empty, out.empty)
        assert torch.equal(fused.voxel_to_camera, out.voxel_to_camera)
        assert torch.equal(fused.reference_columns, out.reference_columns)
        assert torch.equal(fused.column_cost, out.column_cost)
    assert torch.equal(fused.columns, torch_out.columns)
    assert fused.occupancy.any() and bool(fused.empty[3])  # something carved; the empty reference stays empty
    assert fused.cost is None


def test_more_view_slots_than_the_kernel_takes_run_on_torch():
    gen = torch.Generator().manual_seed(12)
    sdf, cams, reference, views = random_proposals(gen, M=8, B=8, V=4, size=24)
    wide = torch.full((8, 70), -1)
    wide[:, :4] = views
    a = carve_proposals(sdf, cams, reference, wide, resolution=10, backend="auto")
    b = carve_proposals(sdf, cams, reference, views, resolution=10, backend="torch")
    assert torch.equal(a.occupancy, b.occupancy)
    if native.available():
        with pytest.raises(ValueError, match="view slots"):
            carve_proposals(sdf, cams, reference, wide, resolution=10, backend="fused")


def test_the_kernel_takes_every_resolution_carve_proposals_takes():
    from carvi_torch.carve.geometry import check_indices
    with pytest.raises(ValueError, match="2048"):
        check_indices(2, torch.tensor([0]), torch.tensor([[1]]), 2049, torch.device("cpu"))
    assert native.MAX_RESOLUTION >= 2048


def test_a_kernel_that_disagrees_with_grid_sample_is_not_used(monkeypatch):
    """The loader's self-test rejects a sample that differs from grid_sample in the last bit."""
    if not native.available():
        pytest.skip(f"kernel unavailable: {native.unavailable_reason()}")
    lib = native.operators()
    real = native._sample_with

    def off_by_an_ulp(lib_, fused, ext, k, scale, grid):
        out = real(lib_, fused, ext, k, scale, grid)
        out[7] = torch.nextafter(out[7], torch.tensor(float("inf")))
        return out

    monkeypatch.setattr(native, "_sample_with", off_by_an_ulp)
    assert native._self_test(lib) is None
    monkeypatch.setattr(native, "_sample_with", real)
    assert native._self_test(lib) == native.variant()
    # the same for the column sampler the carving uses
    real_line = native._line_with

    def line_off(lib_, fused, ext, k, scale, g0, c, m):
        out = real_line(lib_, fused, ext, k, scale, g0, c, m)
        out[-1] = torch.nextafter(out[-1], torch.tensor(float("-inf")))
        return out

    monkeypatch.setattr(native, "_line_with", line_off)
    assert native._self_test(lib) is None
