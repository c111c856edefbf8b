"""The package's compiled C++ library: its build, its cache and its loading.

One shared library holds the package's C++ kernels (``carvi_torch/kernels/``): the fused carving
(``carve_core.h``, used by :mod:`carvi_torch.carve.native`), the rigid SfM's factorisation loop
(``sfm_steps.h``, used by :mod:`carvi_torch.viewpoints.factorization`), the keypoint-only camera fit
(``camera_steps.h``, used by :mod:`carvi_torch.viewpoints.camera_fit`), the SfM's joint bundle adjustment
(``bundle_steps.h``, used by :mod:`carvi_torch.viewpoints.bundle`) and the selection's projection onto the
principal planes (``splat_planes.h``, used by :mod:`carvi_torch.select`), registered as ``torch.library``
operators by ``carve_native.cpp``. This module builds, caches and loads it; the stages that use an operator decide
whether they trust it (the carving runs a self-test first, :func:`carvi_torch.carve.native.available`).

Building. On first use the C++ compiler of the machine (``$CXX``, else ``c++``) builds a plain shared
library against the headers and libraries in torch's wheel (``torch/library.h`` and a few ATen
headers: no Python headers, no pybind11, no ninja, no setuptools; ``-fopenmp`` where torch uses
OpenMP) into ``$CARVI_TORCH_CACHE/kernels`` (default ``~/.cache/carvi_torch``), under a name that
hashes the sources, the flags, the compiler and torch's version (a library is tied to the torch it
was built against); ``torch.ops.load_library`` loads it. Its operators live in the namespace
``carvi_<that hash>``: a second library defining operators of a namespace already registered aborts
the process, so two builds never share one, and a namespace already registered is reused, not loaded
again.

Cache rules (:mod:`carvi_torch.user_cache`): the directory is the user's own, mode 0700; a library is loaded
only when it and its sidecar ``<name>.sha256`` are regular files of this user without group/other write bits and the
library's SHA-256 equals the sidecar's (checked before anything maps the file: a truncated library
can crash the process that loads it); anything else is rebuilt. Builds run under an exclusive lock
of the directory, into a private temporary directory, and are moved into place with ``os.replace``
(library, then sidecar); checks and loads hold a shared lock. No compiler or a failed build makes
:func:`load` report the reason and :func:`library_operators` return ``None``; the stages then run their
torch code.


Example:
    >>> library_path().name.startswith("carve_native-")
    True
"""
from __future__ import annotations

import hashlib
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path

import torch

from .runtime import NO_LOCKS, FileLock
from .user_cache import cache_root, own_file_problem, private_dir

__all__ = ["library_path", "cache_entry_problem", "load", "library_operators", "once"]

_KERNELS = Path(__file__).resolve().parent / "kernels"
_SOURCE = _KERNELS / "carve_native.cpp"
_HEADERS = tuple(_KERNELS / name for name in ("carve_core.h", "sfm_steps.h", "camera_steps.h", "bundle_steps.h",
                                            "splat_planes.h"))
_FLAGS = ["-O3", "-std=c++17", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math",
          "-fno-unsafe-math-optimizations"]
_BUILD_TIMEOUT_S = 600


def _flags() -> list[str]:
    """The compiler flags. ``-fopenmp`` where torch runs its intra-op threads with OpenMP (its Linux wheels):
    ``at::parallel_for`` is inline code that is parallel only when compiled with OpenMP (without it the
    carving silently runs on one thread); the library then shares torch's own ``libgomp.so.1``. Not on
    macOS, whose clang has no ``-fopenmp`` (the carving runs on one thread there; not tried)."""
    openmp = torch.backends.openmp.is_available() and sys.platform != "darwin"
    return _FLAGS + (["-fopenmp"] if openmp else [])


def _compiler() -> list[str]:
    return shlex.split(os.environ.get("CXX") or "c++")


def _cache_dir() -> Path:
    return cache_root()


def _key() -> str:
    """16 hex digits of SHA-256 over what the library depends on: sources, compiler, flags, platform, torch."""
    key = hashlib.sha256()
    for path in (_SOURCE, *_HEADERS):
        key.update(path.read_bytes())
    key.update(" ".join(_compiler() + _flags()).encode())
    for part in (platform.machine(), sys.platform, torch.__version__, str(torch.version.git_version)):
        key.update(part.encode())
    return key.hexdigest()[:16]


def library_path() -> Path:
    """Where the compiled kernel for these sources, compiler, flags and torch lives (built or not)."""
    return _cache_dir() / "kernels" / f"carve_native-{_key()}.so"


def _sidecar(path: Path) -> Path:
    return path.with_name(path.name + ".sha256")


# --------------------------------------------------------------------------- the cache's rules


#: The cache's rules (:mod:`carvi_torch.user_cache`), by their names here.
_private_dir = private_dir
_own_file_problem = own_file_problem


def _sha256(path: Path) -> str:
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_BINARY", 0)
    with os.fdopen(os.open(path, flags), "rb") as f:
        return hashlib.sha256(f.read()).hexdigest()


def cache_entry_problem(path: Path) -> str | None:
    """Why the cached library at ``path`` must not be loaded (``None``: it may). Reads it, never maps it."""
    for p in (path, _sidecar(path)):
        why = _own_file_problem(p)
        if why is not None:
            return why
    recorded = _sidecar(path).read_text(encoding="ascii", errors="replace").strip()
    actual = _sha256(path)
    if recorded != actual:
        return f"{path.name} has SHA-256 {actual[:12]}..., its build recorded {recorded[:12]!r}"
    return None


@contextmanager
def _dir_lock(directory: Path, exclusive: bool):
    """An advisory lock of the cache directory (:class:`~carvi_torch.runtime.FileLock` on its ``.lock``, waited
    for): exclusive to build, shared to check and load. Where the platform has no ``flock`` (Windows) nothing is
    locked: builds stay atomic (``os.replace``), concurrent ones may repeat work; nor where the file system has no
    locks (:data:`~carvi_torch.runtime.NO_LOCKS`: Lustre without ``-o flock``, a read-only NFS lock file)."""
    with FileLock(directory / ".lock", mode=0o600) as lock:
        try:
            lock.lock(exclusive)
        except OSError as e:
            if e.errno not in NO_LOCKS:
                raise
        yield


# --------------------------------------------------------------------------- building and loading


def _torch_dirs() -> tuple[Path, Path]:
    """torch's header and library folders in its wheel (what ``torch.utils.cpp_extension.include_paths()`` and
    ``library_paths()`` return for the CPU; that module is not imported: it needs setuptools)."""
    root = Path(torch.__file__).resolve().parent
    return root / "include", root / "lib"


def _build_command(out: Path, namespace: str, extra: tuple[str, ...] = ()) -> list[str]:
    """The compiler's command line for the library."""
    include, lib = _torch_dirs()
    cmd = _compiler() + _flags() + [f"-DCARVI_NS={namespace}", *extra, "-isystem", str(include)]
    cmd += ["-o", str(out), str(_SOURCE), f"-L{lib}", "-lc10", "-ltorch_cpu"]
    if sys.platform == "darwin":
        cmd += [f"-Wl,-rpath,{lib}"]
    return cmd


def _build(path: Path, namespace: str, extra: tuple[str, ...] = ()) -> None:
    """Compile the library to ``path`` (atomically: a private temporary directory, then ``os.replace``) and
    record its SHA-256 beside it. The caller holds the directory's exclusive lock."""
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=path.parent))
    try:
        out = tmp / path.name
        cmd = _build_command(out, namespace, extra)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=_BUILD_TIMEOUT_S)
        except OSError as exc:  # no such compiler
            raise RuntimeError(f"no C++ compiler to build the kernels ({cmd[0]}): {exc}") from exc
        if proc.returncode != 0 or not out.is_file():
            raise RuntimeError(f"compiling the kernels' library failed ({shlex.join(cmd)}):\n"
                               f"{proc.stderr.strip()[-4000:]}")
        os.chmod(out, 0o700)
        digest = _sha256(out)
        (tmp / "sha256").write_text(digest + "\n", encoding="ascii")
        os.chmod(tmp / "sha256", 0o600)
        os.replace(out, path)
        os.replace(tmp / "sha256", _sidecar(path))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _ops(namespace: str):
    """The operators of ``namespace`` when they are registered in this process, else ``None``."""
    ops = getattr(torch.ops, namespace)
    try:
        ops.carve_labels  # noqa: B018 -- raises when the namespace has no such operator
    except (AttributeError, RuntimeError):
        return None
    return ops


def _open_library():
    """Load the cached library (building it first when it is missing or fails the cache's rules); its operators.

    A library is loaded at most once per process under one namespace: a second library registering the
    same namespace would abort the process, so an already registered namespace is reused."""
    key = _key()
    namespace = f"carvi_{key}"
    path = _private_dir(_cache_dir() / "kernels") / f"carve_native-{key}.so"
    if _ops(namespace) is not None:
        return _ops(namespace), path, None
    with _dir_lock(path.parent, exclusive=False):
        if cache_entry_problem(path) is None:
            torch.ops.load_library(str(path))
            return _ops(namespace), path, None
    with _dir_lock(path.parent, exclusive=True):
        why = cache_entry_problem(path)  # another process may have built it meanwhile
        if why is not None:
            _build(path, namespace)
            problem = cache_entry_problem(path)
            if problem is not None:
                raise RuntimeError(f"the freshly built kernel fails the cache's checks: {problem}")
        torch.ops.load_library(str(path))
        return _ops(namespace), path, why


_lock = threading.RLock()
_state: dict = {}


def _after_fork_in_child() -> None:
    """A child forked while another thread held the lock (during a build, say) would wait on it forever."""
    global _lock
    _lock = threading.RLock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def once(state: dict, fill) -> dict:
    """``state``, filled by ``fill(state)`` the first time (under one process-wide re-entrant lock, fresh in a
    forked child), so that a library is built, loaded and checked once per process, whichever thread asks
    first. :func:`load` and the carving's self-test (:mod:`carvi_torch.carve.native`) share it."""
    with _lock:
        if not state:
            fill(state)
        return state


def _fill(state: dict) -> None:
    try:
        ops, path, rebuilt = _open_library()
        if ops is None:
            raise RuntimeError(f"{path.name} loaded but registered no operators")
        state.update(ops=ops, path=path, rebuilt=rebuilt, reason=None)
    except Exception as exc:  # noqa: BLE001 -- whatever fails, the stages run their torch code
        state.update(ops=None, path=None, rebuilt=None, reason=f"{type(exc).__name__}: {exc}")


def load() -> dict:
    """Build (when needed) and load the library once per process: ``ops`` (``torch.ops.<namespace>``, or
    ``None``), ``path``, ``rebuilt`` (why this process built it; ``None`` when it was loaded as found) and
    ``reason`` (why ``ops`` is ``None``)."""
    return once(_state, _fill)


def library_operators():
    """The library's operators (``None`` where it did not build or load; :func:`load` says why)."""
    return load()["ops"]


def operators_on(device, *, required: bool = False):
    """The library's operators for tensors on ``device``: ``None`` off the CPU (the kernels take CPU tensors) or where
    the library did not build or load. ``required``: an error instead of ``None`` (``ValueError`` off the CPU,
    ``RuntimeError`` with :func:`load`'s reason where the library is missing)."""
    if torch.device(device).type != "cpu":
        if required:
            raise ValueError(f"the compiled kernels need CPU tensors, got {device}")
        return None
    ops = library_operators()
    if ops is None and required:
        raise RuntimeError(f"the compiled library is not available: {load()['reason']}")
    return ops
