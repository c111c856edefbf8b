"""The fused CPU carving kernel as torch operators: sampling, maximum and labels in one pass, with early exit.

:func:`carvi_torch.carve.carve_proposals` computes the cone cost ``C`` of every voxel of every
foreground column with one ``grid_sample`` call per view, then labels the voxels. Most of those
samples are not needed for the labels: a voxel is exterior as soon as one view gives a value
``>= 0`` (``C`` is a maximum), so the rest of its views need not be read. torch has no operator
that stops sampling early, so this module compiles a small C++ kernel (``kernels/carve_core.h``,
wrapped in ``torch.library`` operators by ``kernels/carve_native.cpp``) that walks each column in
depth order and reads a voxel's views only until the labels are decided (see the header for the
exact rule, which keeps the imprinting's first minimum exact too).

Exactness. The kernel repeats the torch path's float32 arithmetic operation for operation. Whether
torch's CPU ``grid_sample`` sums its four weighted pixels with fused multiply-adds depends on how
it was built for this processor (it does in its AVX2 and AVX-512 kernels), so at load time a
self-test compares both variants of the kernel's sample with ``grid_sample`` bit for bit on
random maps and coordinates, and keeps the one that matches. If neither does, the kernel is not
used, and ``backend="auto"`` falls back to torch.

Building. On first use the C++ compiler of the machine (``$CXX``, else ``c++``) builds a plain shared
library against the headers and libraries in torch's wheel (``torch/library.h`` and a few ATen
headers: no Python headers, no pybind11, no ninja, no setuptools; ``-fopenmp`` where torch uses
OpenMP) into ``$CARVI_TORCH_CACHE/kernels`` (default ``~/.cache/carvi_torch``), under a name that
hashes the sources, the flags, the compiler and torch's version (a library is tied to the torch it
was built against); ``torch.ops.load_library`` loads it. Its operators live in the namespace
``carvi_<that hash>``: a second library defining operators of a namespace already registered aborts
the process, so two builds never share one, and a namespace already registered is reused, not loaded
again.

Cache rules: the directory is the user's own, mode 0700; a library is loaded only when it and its
sidecar ``<name>.sha256`` are regular files of this user without group/other write bits and the
library's SHA-256 equals the sidecar's (checked before anything maps the file: a truncated library
can crash the process that loads it); anything else is rebuilt. Builds run under an exclusive lock
of the directory, into a private temporary directory, and are moved into place with ``os.replace``
(library, then sidecar); checks and loads hold a shared lock. No compiler, a failed build or a
failed self-test makes :func:`available` ``False`` with the reason in :func:`unavailable_reason`;
nothing else changes.

Threads. The operator carves in torch's intra-op thread pool (``at::parallel_for``), so
``torch.set_num_threads`` governs it; its threads take proposals one at a time, heaviest first. The
dispatcher releases the GIL during the call. No fork handling: a forked child is in the state of
every torch operator there (with GNU OpenMP, a child that runs a parallel region after its parent
ran one waits forever, whichever operator it is, unless it sets ``torch.set_num_threads(1)``).

The same library holds the rigid SfM's factorisation loop (``kernels/sfm_steps.h``, operator ``sfm_factorize``,
used by :mod:`carvi_torch.viewpoints.sfm` through :func:`library_operators`): it samples no maps, so it is
available whenever the library loads, whatever the self-test says.

NaN. A NaN sample does not win the kernel's maximum, while ``torch.maximum`` propagates it; the
carving never sees one (the maps and the cameras are checked finite).

Example:
    >>> isinstance(available(), bool)
    True
"""
from __future__ import annotations

import hashlib
import os
import platform
import shlex
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import torch

from ..cameras import ScaledOrthographic, random_rotations
from .geometry import prepare_maps
from .torch_backend import carve_torch, grid_sample_maps, kernel_inputs, sample_planes

try:
    import fcntl
except ImportError:  # Windows: no advisory locks; builds stay atomic (os.replace), concurrent ones may repeat work
    fcntl = None

__all__ = ["available", "unavailable_reason", "carve_labels", "sample", "variant", "library_path", "status",
           "operators", "library_operators", "cache_entry_problem", "MAX_VIEWS", "MAX_RESOLUTION"]
#: Largest resolution the kernel takes (``CARVI_MAX_RESOLUTION`` in the C++ source).
MAX_RESOLUTION = 2048
#: Most view slots a proposal may use (``CARVI_MAX_VIEWS`` in the C++ source).
MAX_VIEWS = 64

_KERNELS = Path(__file__).resolve().parent / "kernels"
_SOURCE = _KERNELS / "carve_native.cpp"
_HEADERS = (_KERNELS / "carve_core.h", _KERNELS / "sfm_steps.h")
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


_lock = threading.Lock()
_state: dict = {}


def _after_fork_in_child() -> None:
    """A child forked while another thread held the lock (during a build, say) would wait on it forever."""
    global _lock
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def _compiler() -> list[str]:
    return shlex.split(os.environ.get("CXX") or "c++")


def _cache_dir() -> Path:
    root = os.environ.get("CARVI_TORCH_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "carvi_torch"


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


def _private_dir(path: Path) -> Path:
    """``path`` as a directory of this user, mode 0700 (created so; an existing one of ours is tightened).

    Raises ``PermissionError`` for a directory of another user or a symbolic link."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)  # the mode applies to the root only if created
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    st = os.lstat(path)
    if not stat.S_ISDIR(st.st_mode):
        raise PermissionError(f"the kernel cache {path} is not a directory (a link?)")
    if os.name == "posix":
        if st.st_uid != os.getuid():
            raise PermissionError(f"the kernel cache {path} belongs to uid {st.st_uid}, not to this user "
                                  f"({os.getuid()})")
        if stat.S_IMODE(st.st_mode) != 0o700:
            os.chmod(path, 0o700)
    return path


def _own_file_problem(path: Path) -> str | None:
    """Why ``path`` is not a regular file of this user without group/other write bits (``None`` when it is)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return f"{path.name} is missing"
    if not stat.S_ISREG(st.st_mode):
        return f"{path.name} is not a regular file"
    if os.name == "posix" and st.st_uid != os.getuid():
        return f"{path.name} belongs to uid {st.st_uid}, not {os.getuid()}"
    if os.name == "posix" and st.st_mode & 0o022:
        return f"{path.name} is writable by others (mode {stat.S_IMODE(st.st_mode):o})"
    return None


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
    """An advisory lock of the cache directory: exclusive to build, shared to check and load (POSIX)."""
    if fcntl is None:
        yield
        return
    fd = os.open(directory / ".lock", os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o600)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        yield
    finally:
        os.close(fd)  # releases the lock


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
            raise RuntimeError(f"no C++ compiler to build the fused carving kernel ({cmd[0]}): {exc}") from exc
        if proc.returncode != 0 or not out.is_file():
            raise RuntimeError(f"compiling the fused carving kernel failed ({shlex.join(cmd)}):\n"
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


def _load() -> dict:
    with _lock:
        if _state:
            return _state
        try:
            ops, path, rebuilt = _open_library()
            if ops is None:
                raise RuntimeError(f"{path.name} loaded but registered no carving operators")
            _state["library"] = ops
            name = _self_test(ops)
            if name is None:
                raise RuntimeError("the kernel's bilinear samples differ from torch's grid_sample on this machine "
                                   f"(CPU capability {torch.backends.cpu.get_cpu_capability()}), so its labels "
                                   "could differ from the torch carving's")
            _state.update(ops=ops, variant=name, reason=None, path=path, rebuilt=rebuilt)
        except Exception as exc:  # noqa: BLE001 -- whatever fails, the torch carving runs instead
            _state.update(ops=None, variant=None, reason=f"{type(exc).__name__}: {exc}", path=None, rebuilt=None)
        return _state


def operators():
    """The loaded operators (``torch.ops.<namespace>``: ``carve_labels``, ``sample``, ``line``, ``has_fma``),
    or ``None`` where the kernel is not available."""
    return _load()["ops"]


def library_operators():
    """The library's operators whether or not the carving's self-test passed (``None`` where it did not build
    or load): its ``sfm_factorize`` (the rigid SfM's factorisation, ``kernels/sfm_steps.h``) does not sample
    maps, so the self-test's bilinear samples do not concern it."""
    return _load().get("library")


def status() -> dict:
    """``available``, ``variant``, ``reason`` (why not available), ``path`` of the library and ``rebuilt``
    (why this process built it: no library yet, or the one found failed a check; ``None`` when loaded)."""
    s = _load()
    return {"available": s["ops"] is not None, "variant": s["variant"], "reason": s["reason"],
            "path": None if s["path"] is None else str(s["path"]), "rebuilt": s["rebuilt"]}


def available() -> bool:
    """Whether the fused kernel is built, loaded and bit-exact with ``grid_sample`` here (builds it on first call)."""
    return _load()["ops"] is not None


def unavailable_reason() -> str | None:
    """Why :func:`available` is ``False`` (``None`` when it is available)."""
    return _load()["reason"]


def variant() -> str | None:
    """The sample arithmetic in use: ``"fma"`` (fused multiply-adds, as torch's AVX2/AVX-512 kernels) or ``"plain"``."""
    return _load()["variant"]


def _library():
    state = _load()
    if state["ops"] is None:
        raise RuntimeError(f"the fused carving kernel is not available: {state['reason']}")
    return state["ops"], state["variant"] == "fma"


# --------------------------------------------------------------------------- the self-test


def _reference() -> SimpleNamespace:
    """The torch carving's pieces the self-test compares the kernel with (the one place that names them)."""
    return SimpleNamespace(grid_sample=grid_sample_maps, sample_planes=sample_planes, fused_inputs=kernel_inputs,
                           carve_torch=carve_torch, prepare_maps=prepare_maps, ScaledOrthographic=ScaledOrthographic,
                           random_rotations=random_rotations)


def _sample_with(ops, fused: bool, ext: torch.Tensor, k: int, scale: float, grid: torch.Tensor) -> torch.Tensor:
    """``(m,)`` samples of map ``k`` of ``ext (K, Hp, Wp)`` scaled, at ``grid (m, 2)`` (one point at a time)."""
    return ops.sample(ext, k, scale, grid.contiguous(), fused)


def _line_with(ops, fused: bool, ext: torch.Tensor, k: int, scale: float, g0: tuple[float, float],
               c: tuple[float, float], m: int) -> torch.Tensor:
    """``(m,)`` samples at depths ``0 .. m - 1`` of one column (``g0 d + c``), read as the carving reads them."""
    return ops.line(ext, k, scale, g0[0], g0[1], c[0], c[1], m, fused)


def _self_test(ops) -> str | None:
    """The sample variant that equals ``grid_sample`` bit for bit here (``"fma"`` or ``"plain"``), or ``None``.

    Checks both ways the kernel reads a map: one point at a time, and along columns (depths ``0 .. m - 1``
    of a line, eight at a time where the processor allows), then the labels of a small carving."""
    ref = _reference()
    gen = torch.Generator().manual_seed(0)
    cases = []
    for Hp, Wp in ((37, 53), (130, 97), (2, 3)):
        ext = torch.randn(2, Hp, Wp, generator=gen) * 40
        grid = torch.rand(20000, 2, generator=gen) * 2.4 - 1.2  # inside, on and beyond the border
        grid[:500] = torch.round(grid[:500] * 8) / 8  # pixel centres and edges
        scale = float(torch.rand((), generator=gen) * 2 + 0.25)
        want = ref.grid_sample((ext[1] * scale)[None, None], grid.view(1, 1, -1, 2)).view(-1)
        cases.append((ext, scale, grid, want))
    lines = []
    for _ in range(45):
        ext, scale, _, _ = cases[len(lines) % 3]
        g0 = tuple((torch.rand(2, generator=gen) * 0.2 - 0.1).tolist())
        c = tuple((torch.rand(2, generator=gen) * 2.4 - 1.2).tolist())
        m = int(torch.randint(1, 200, (), generator=gen))
        # depths 0 .. m - 1 of one column: depth term g0 d plus column term c
        dz = torch.tensor(g0, dtype=torch.float32)[None, :, None] * torch.arange(m, dtype=torch.float32)
        want = ref.sample_planes((ext[1] * scale)[None, None], dz, torch.tensor(c)[None, :, None]).view(-1)
        lines.append((ext, scale, g0, c, m, want))
    for name in ("fma", "plain") if ops.has_fma() else ("plain",):
        fused = name == "fma"
        if all(torch.equal(_sample_with(ops, fused, ext, 1, scale, grid), want) for ext, scale, grid, want in cases) \
                and all(torch.equal(_line_with(ops, fused, ext, 1, scale, g0, c, m), want)
                        for ext, scale, g0, c, m, want in lines) \
                and _labels_agree(ops, fused, gen, ref):
            return name
    return None


def _labels_agree(ops, fused: bool, gen: torch.Generator, ref: SimpleNamespace) -> bool:
    """The kernel's labels equal the torch carving's on a small random problem (every step of the
    arithmetic, the column terms included, as the compiler built it)."""
    M, size, n = 6, 24, 12
    yy, xx = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                            indexing="ij")
    centre = 8 + 8 * torch.rand(M, 2, generator=gen)
    radius = 4 + 4 * torch.rand(M, 2, generator=gen)
    sdf = torch.sqrt(((xx - centre[:, 0, None, None]) / radius[:, 0, None, None]) ** 2
                     + ((yy - centre[:, 1, None, None]) / radius[:, 1, None, None]) ** 2) * 5 - 5
    cams = ref.ScaledOrthographic(ref.random_rotations(M, generator=gen).float(),
                                  1 + 0.2 * torch.rand(M, generator=gen), centre.clone())
    maps = ref.prepare_maps(sdf, cams)
    reference = torch.arange(M)
    views = torch.stack([(reference + k) % M for k in (1, 2, 3)], 1)
    want = ref.carve_torch(maps, reference, views, n)
    ext, slots, scale, G, column_cost, _ = ref.fused_inputs(maps, reference, views, n)
    occ, columns, nonempty, _ = ops.carve_labels(ext, slots, scale, G, column_cost, n, True, fused)
    return bool(torch.equal(occ.view(want.occupancy.shape), want.occupancy) and torch.equal(~nonempty, want.empty))


# --------------------------------------------------------------------------- the public calls


def sample(ext: torch.Tensor, k: int, scale: float, grid: torch.Tensor) -> torch.Tensor:
    """The kernel's bilinear sample of map ``k`` of ``ext`` scaled by ``scale``.

    Equal bit for bit to ``grid_sample((ext[k] * scale)[None, None], grid.view(1, 1, -1, 2),
    mode="bilinear", padding_mode="border", align_corners=True)``.

    Args:
        ext: ``(K, Hp, Wp)`` CPU maps (made float32 and contiguous).
        k: the map.
        scale: float32 factor of its values.
        grid: ``(m, 2)`` normalised ``(x, y)`` coordinates (made float32).

    Returns:
        ``(m,)`` float32 samples.

    Example:
        >>> ext = torch.arange(6.0).view(1, 2, 3)
        >>> sample(ext, 0, 1.0, torch.tensor([[0.0, 0.0]])) if available() else torch.tensor([2.5])
        tensor([2.5000])
    """
    ops, fused = _library()
    ext = ext.to(torch.float32).contiguous()
    return _sample_with(ops, fused, ext, int(k), float(scale), grid.to(torch.float32).reshape(-1, 2))


def carve_labels(ext: torch.Tensor, views: torch.Tensor, scale: torch.Tensor, G: torch.Tensor,
                 column_cost: torch.Tensor, resolution: int, imprint: bool, variant: str | None = None):
    """Interior labels of ``B`` proposals by the fused kernel (what :func:`carvi_torch.carve.carve_proposals` runs
    on the CPU with ``backend="fused"``).

    Args:
        ext: ``(K + 1, H + 2 PAD, W + 2 PAD)`` float32 extended maps, unscaled
            (:attr:`carvi_torch.carve.geometry.CarveMaps.ext`: the ``K`` maps, then the unused-slot map).
        views: ``(B, V)`` int64 rows of ``ext`` per view slot, ``-1`` for an unused slot (``V <= MAX_VIEWS``).
        scale: ``(B, V)`` float32 per-slot scale of the map values.
        G: ``(B, V, 2, 4)`` float32 voxel index -> sampling coordinates
            (:func:`carvi_torch.carve.geometry.proposal_geometry`).
        column_cost: ``(B, n * n)`` float32 reference cost at the column centres.
        resolution: ``n`` (1 to ``MAX_RESOLUTION``).
        imprint: imprint the foreground columns left without an interior voxel.
        variant: ``"fma"`` or ``"plain"`` to force a sample arithmetic (tests); default the one the
            self-test found equal to ``grid_sample`` (:func:`variant`).

    Returns:
        ``occ (B, n, n * n)`` bool (depth, then the flat column ``h * n + w``), ``columns (B, n * n)`` bool,
        ``nonempty (B,)`` bool, ``samples (B,)`` int64: the bilinear samples read per proposal.

    Raises:
        ValueError: a tensor not on the CPU, of the wrong shape, views out of range, too many view
            slots, a resolution out of range, an unknown variant. TypeError: a wrong dtype.
    """
    ops, fused = _library()
    if variant is not None:
        if variant not in ("fma", "plain") or (variant == "fma" and not ops.has_fma()):
            raise ValueError(f"variant must be 'plain' or (on a processor with AVX2 and FMA) 'fma', got {variant!r}")
        fused = variant == "fma"
    tensors = [t.contiguous() if isinstance(t, torch.Tensor) else t for t in (ext, views, scale, G, column_cost)]
    return ops.carve_labels(*tensors, int(resolution), bool(imprint), fused)
