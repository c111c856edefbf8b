"""The fused CPU carving kernel: sampling, maximum and labels in one pass, with early exit.

:func:`carvi_torch.carve.carve_proposals` computes the cone cost ``C`` of every voxel of every
foreground column with one ``grid_sample`` call per view, then labels the voxels. Most of those
samples are not needed for the labels: a voxel is exterior as soon as one view gives a value
``>= 0`` (``C`` is a maximum), so the rest of its views need not be read. torch has no operator
that stops sampling early, so this module compiles a small C kernel
(``carvi_torch/carve/kernels/carve_fused.c``) that walks each column in depth order and reads a
voxel's views only until the labels are decided (see the C file for the exact rule, which keeps
the imprinting's first minimum exact too).

Exactness. The kernel repeats the torch path's float32 arithmetic operation for operation. Whether
torch's CPU ``grid_sample`` sums its four weighted pixels with fused multiply-adds depends on how
it was built for this processor (it does in its AVX2 and AVX-512 kernels), so at load time a
self-test compares both variants of the kernel's sample with ``grid_sample`` bit for bit on
random maps and coordinates, and keeps the one that matches. If neither does, the kernel is not
used (the labels could then differ from the torch path's), and ``backend="auto"`` falls back to
torch.

Building. The kernel is compiled on first use with the C compiler of the machine (``$CC``, else
Python's, else ``cc``) into ``$CARVI_TORCH_CACHE/kernels`` (default ``~/.cache/carvi_torch``),
under a name that hashes the source, the flags and the compiler, written atomically; later runs
load it. No compiler, a failed build or a failed self-test makes :func:`available` ``False``
with the reason in :func:`unavailable_reason`; nothing else changes.

Threads. ``ctypes`` releases the GIL during a call, so proposals are split into four contiguous
ranges per torch intra-op thread (of about equal estimated work) and carved by that many Python
threads of a pool kept across calls (and forgotten in a forked child, where its threads do not
exist).

NaN. A NaN sample does not win the kernel's maximum, while ``torch.maximum`` propagates it; the
carving never sees one (:func:`carvi_torch.carve.geometry.prepare_maps` and the cameras are checked finite).

Example:
    >>> from carvi_torch.carve import native
    >>> isinstance(native.available(), bool)
    True
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shlex
import subprocess
import sysconfig
import tempfile
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from ..cameras import ScaledOrthographic, random_rotations
from .geometry import prepare_maps
from .torch_backend import carve_torch, grid_sample_maps, kernel_inputs, sample_planes

__all__ = ["available", "unavailable_reason", "carve_labels", "sample", "variant", "library_path", "MAX_VIEWS",
           "MAX_RESOLUTION"]

_SOURCE = Path(__file__).with_name("kernels") / "carve_fused.c"
_FLAGS = ["-O3", "-std=c99", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math",
          "-fno-unsafe-math-optimizations"]
#: Largest resolution the kernel takes (``MAX_RESOLUTION`` in the C source).
MAX_RESOLUTION = 2048
#: Most view slots a proposal may use (``MAX_VIEWS`` in the C source).
MAX_VIEWS = 64

_lock = threading.Lock()
_state: dict = {}


def _after_fork_in_child() -> None:
    """A forked child inherits the pools' executors without their threads, and maybe a held lock."""
    global _lock
    _lock = threading.Lock()
    _pools.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def _compiler() -> list[str]:
    cc = os.environ.get("CC") or sysconfig.get_config_var("CC") or "cc"
    return shlex.split(cc)


def _cache_dir() -> Path:
    root = os.environ.get("CARVI_TORCH_CACHE")
    return Path(root) if root else Path.home() / ".cache" / "carvi_torch"


def library_path() -> Path:
    """Where the compiled kernel for this source, compiler and flags lives (built or not)."""
    cc = _compiler()
    key = hashlib.sha256()
    key.update(_SOURCE.read_bytes())
    key.update(" ".join(cc + _FLAGS).encode())
    key.update(platform.machine().encode())
    return _cache_dir() / "kernels" / f"carve_fused-{key.hexdigest()[:16]}.so"


def _build(path: Path, extra: tuple[str, ...] = ()) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=path.parent)
    os.close(fd)
    try:
        cmd = _compiler() + _FLAGS + list(extra) + ["-o", tmp, str(_SOURCE), "-lm"]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if proc.returncode != 0:
            raise RuntimeError(f"compiling the fused carving kernel failed ({' '.join(cmd)}):\n{proc.stderr.strip()}")
        os.replace(tmp, path)  # atomic: a concurrent process loads either nothing or the whole library
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def _declare(lib) -> None:
    P, I64, F32, I = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_int
    for name in ("carvi_sample_plain", "carvi_sample_fma"):
        fn = getattr(lib, name)
        fn.argtypes = [P, I64, I64, I64, F32, P, P, I64, P]
        fn.restype = None
    for name in ("carvi_line_plain", "carvi_line_fma"):
        fn = getattr(lib, name)
        fn.argtypes = [P, I64, I64, I64, F32, F32, F32, F32, F32, I64, P]
        fn.restype = None
    for name in ("carvi_carve_plain", "carvi_carve_fma"):
        fn = getattr(lib, name)
        fn.argtypes = [P, I64, I64, P, P, P, P, I64, I64, I, I64, I64, P, P, P, P]
        fn.restype = I
    lib.carvi_has_fma.argtypes = []
    lib.carvi_has_fma.restype = I


def _ptr(t: torch.Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


def _sample_with(lib, fused: bool, ext: torch.Tensor, k: int, scale: float, grid: torch.Tensor) -> torch.Tensor:
    gx, gy = grid[:, 0].contiguous(), grid[:, 1].contiguous()
    out = torch.empty(grid.shape[0], dtype=torch.float32)
    fn = lib.carvi_sample_fma if fused else lib.carvi_sample_plain
    fn(_ptr(ext), ext.shape[1], ext.shape[2], k, scale, _ptr(gx), _ptr(gy), grid.shape[0], _ptr(out))
    return out


def _line_with(lib, fused: bool, ext: torch.Tensor, k: int, scale: float, g0: tuple[float, float],
               c: tuple[float, float], m: int) -> torch.Tensor:
    if not 0 < m <= MAX_RESOLUTION:
        raise ValueError(f"a line has 1 to {MAX_RESOLUTION} depths, got {m}")
    out = torch.empty(m, dtype=torch.float32)
    fn = lib.carvi_line_fma if fused else lib.carvi_line_plain
    fn(_ptr(ext), ext.shape[1], ext.shape[2], k, scale, g0[0], g0[1], c[0], c[1], m, _ptr(out))
    return out


def _self_test(lib) -> str | None:
    """The sample variant that equals ``grid_sample`` bit for bit here (``"fma"`` or ``"plain"``), or ``None``.

    Checks both ways the kernel reads a map: one point at a time, and along columns (depths ``0 .. m - 1``
    of a line, as the carving reads them, eight at a time where the processor allows). The references
    are the torch carving's own calls (:func:`~carvi_torch.carve.torch_backend.grid_sample_maps`, and
    :func:`~carvi_torch.carve.torch_backend.sample_planes` for the columns' coordinate arithmetic)."""
    gen = torch.Generator().manual_seed(0)
    cases = []
    for Hp, Wp in ((37, 53), (130, 97), (2, 3)):
        # one value beyond the last map: the column sampler may read it (with weight 0)
        ext = _padded(torch.randn(2, Hp, Wp, generator=gen) * 40)
        grid = torch.rand(20000, 2, generator=gen) * 2.4 - 1.2  # inside, on and beyond the border
        grid[:500] = torch.round(grid[:500] * 8) / 8  # pixel centres and edges
        scale = float(torch.rand((), generator=gen) * 2 + 0.25)
        want = grid_sample_maps((ext[1] * scale)[None, None], grid.view(1, 1, -1, 2)).view(-1)
        cases.append((ext, scale, grid, want))
    lines = []
    for _ in range(45):
        ext, scale, _, _ = cases[len(lines) % 3]
        g0 = tuple((torch.rand(2, generator=gen) * 0.2 - 0.1).tolist())
        c = tuple((torch.rand(2, generator=gen) * 2.4 - 1.2).tolist())
        m = int(torch.randint(1, 200, (), generator=gen))
        # depths 0 .. m - 1 of one column: depth term g0 d plus column term c
        dz = torch.tensor(g0, dtype=torch.float32)[None, :, None] * torch.arange(m, dtype=torch.float32)
        want = sample_planes((ext[1] * scale)[None, None], dz, torch.tensor(c)[None, :, None]).view(-1)
        lines.append((ext, scale, g0, c, m, want))
    order = ("fma", "plain") if lib.carvi_has_fma() else ("plain",)
    for name in order:
        fused = name == "fma"
        if all(torch.equal(_sample_with(lib, fused, ext, 1, scale, grid), want) for ext, scale, grid, want in cases) \
                and all(torch.equal(_line_with(lib, fused, ext, 1, scale, g0, c, m), want)
                        for ext, scale, g0, c, m, want in lines) \
                and _labels_agree(lib, fused, gen):
            return name
    return None


def _labels_agree(lib, fused: bool, gen: torch.Generator) -> bool:
    """The kernel's labels equal the torch carving's on a small random problem (every step of the
    arithmetic, the column terms included, as the compiler built it)."""

    M, size, n = 6, 24, 12
    yy, xx = torch.meshgrid(torch.arange(size, dtype=torch.float32), torch.arange(size, dtype=torch.float32),
                            indexing="ij")
    centre = 8 + 8 * torch.rand(M, 2, generator=gen)
    radius = 4 + 4 * torch.rand(M, 2, generator=gen)
    sdf = torch.sqrt(((xx - centre[:, 0, None, None]) / radius[:, 0, None, None]) ** 2
                     + ((yy - centre[:, 1, None, None]) / radius[:, 1, None, None]) ** 2) * 5 - 5
    cams = ScaledOrthographic(random_rotations(M, generator=gen).float(), 1 + 0.2 * torch.rand(M, generator=gen),
                              centre.clone())
    maps = prepare_maps(sdf, cams)
    reference = torch.arange(M)
    views = torch.stack([(reference + k) % M for k in (1, 2, 3)], 1)
    want = carve_torch(maps, reference, views, n)
    ext, slots, scale, G, column_cost, _ = kernel_inputs(maps, reference, views, n)
    occ, columns, nonempty, _ = _carve_with(lib, fused, ext, slots, scale, G, column_cost, n, True, 1)
    return bool(torch.equal(occ.view(want.occupancy.shape), want.occupancy) and torch.equal(~nonempty, want.empty))


def _padded(ext: torch.Tensor) -> torch.Tensor:
    """``ext`` (float32) in storage with one more value after it: reading one pixel past its last map is safe."""
    buf = torch.zeros(ext.numel() + 1, dtype=torch.float32)
    buf[:-1] = ext.reshape(-1)
    return buf[:-1].view(ext.shape)


def _load() -> dict:
    with _lock:
        if _state:
            return _state
        try:
            path = library_path()
            if not path.is_file():
                _build(path)
            try:
                lib = ctypes.CDLL(str(path))
                _declare(lib)
            except (OSError, AttributeError):  # a damaged or stale file under the expected name: build again
                _build(path)
                lib = ctypes.CDLL(str(path))
                _declare(lib)
            name = _self_test(lib)
            if name is None:
                raise RuntimeError("the kernel's bilinear samples differ from torch's grid_sample on this machine "
                                   f"(CPU capability {torch.backends.cpu.get_cpu_capability()}), so its labels "
                                   "could differ from the torch carving's")
            _state.update(lib=lib, variant=name, reason=None)
        except Exception as exc:  # noqa: BLE001 -- whatever fails, the torch carving runs instead
            _state.update(lib=None, variant=None, reason=f"{type(exc).__name__}: {exc}")
        return _state


def available() -> bool:
    """Whether the fused kernel is built, loaded and bit-exact with ``grid_sample`` here (builds it on first call)."""
    return _load()["lib"] is not None


def unavailable_reason() -> str | None:
    """Why :func:`available` is ``False`` (``None`` when it is available)."""
    return _load()["reason"]


def variant() -> str | None:
    """The sample arithmetic in use: ``"fma"`` (fused multiply-adds, as torch's AVX2/AVX-512 kernels) or ``"plain"``."""
    return _load()["variant"]


def _library():
    state = _load()
    if state["lib"] is None:
        raise RuntimeError(f"the fused carving kernel is not available: {state['reason']}")
    return state["lib"], state["variant"] == "fma"


def sample(ext: torch.Tensor, k: int, scale: float, grid: torch.Tensor) -> torch.Tensor:
    """The kernel's bilinear sample of map ``k`` of ``ext`` scaled by ``scale``.

    Equal bit for bit to ``grid_sample((ext[k] * scale)[None, None], grid.view(1, 1, -1, 2),
    mode="bilinear", padding_mode="border", align_corners=True)``.

    Args:
        ext: ``(K, Hp, Wp)`` float32 contiguous CPU maps.
        k: the map.
        scale: float32 factor of its values.
        grid: ``(m, 2)`` float32 normalised ``(x, y)`` coordinates.

    Returns:
        ``(m,)`` float32 samples.

    Example:
        >>> ext = torch.arange(6.0).view(1, 2, 3)
        >>> sample(ext, 0, 1.0, torch.tensor([[0.0, 0.0]])) if available() else torch.tensor([2.5])
        tensor([2.5000])
    """
    lib, fused = _library()
    ext = ext.to(torch.float32).contiguous()
    return _sample_with(lib, fused, ext, int(k), float(scale), grid.to(torch.float32).reshape(-1, 2))


#: Ranges of proposals per thread in one :func:`carve_labels` call.
_RANGES_PER_THREAD = 4
_pools: dict[int, ThreadPoolExecutor] = {}


def _pool(threads: int) -> ThreadPoolExecutor:
    """A thread pool of ``threads`` workers, kept for later calls (the carving calls once per chunk)."""
    with _lock:
        if threads not in _pools:
            _pools[threads] = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="carvi-carve")
        return _pools[threads]


def _ranges(weights: list[int], parts: int) -> list[tuple[int, int]]:
    """Split ``range(len(weights))`` into at most ``parts`` contiguous ranges of about equal total weight."""
    total = sum(weights)
    if parts <= 1 or total == 0 or len(weights) <= 1:
        return [(0, len(weights))]
    out, start, acc = [], 0, 0
    for i, w in enumerate(weights):
        acc += w
        if acc * parts >= total * (len(out) + 1) and len(out) < parts - 1:
            out.append((start, i + 1))
            start = i + 1
    if start < len(weights):
        out.append((start, len(weights)))
    return out


def carve_labels(ext: torch.Tensor, views: torch.Tensor, scale: torch.Tensor, G: torch.Tensor,
                 column_cost: torch.Tensor, resolution: int, imprint: bool, threads: int | None = None,
                 variant: str | None = None):
    """Interior labels of ``B`` proposals by the fused kernel (what :func:`carvi_torch.carve.carve_proposals` runs
    on the CPU with ``backend="fused"``).

    Args:
        ext: ``(K, Hp, Wp)`` float32 extended maps, unscaled (:attr:`carvi_torch.carve.geometry.CarveMaps.ext`).
        views: ``(B, V)`` long rows of ``ext`` per view slot, ``-1`` for an unused slot.
        scale: ``(B, V)`` float32 per-slot scale of the map values.
        G: ``(B, V, 2, 4)`` float32 voxel index -> sampling coordinates
            (:func:`carvi_torch.carve.geometry.proposal_geometry`).
        column_cost: ``(B, n * n)`` float32 reference cost at the column centres.
        resolution: ``n``.
        imprint: imprint the foreground columns left without an interior voxel.
        threads: Python threads carving at once (default ``torch.get_num_threads()``).
        variant: ``"fma"`` or ``"plain"`` to force a sample arithmetic (tests); default the one the
            self-test found equal to ``grid_sample`` (:func:`variant`).

    Returns:
        ``occ (B, n, n * n)`` bool (depth, then the flat column ``h * n + w``), ``columns (B, n * n)`` bool,
        ``nonempty (B,)`` bool, ``samples (B,)`` long: the bilinear samples read per proposal.
    """
    lib, fused = _library()
    if variant is not None:
        if variant not in ("fma", "plain") or (variant == "fma" and not lib.carvi_has_fma()):
            raise ValueError(f"variant must be 'plain' or (on a processor with AVX2 and FMA) 'fma', got {variant!r}")
        fused = variant == "fma"
    n = int(resolution)
    _check_inputs(ext, views, scale, G, column_cost, n)
    return _carve_with(lib, fused, ext, views, scale, G, column_cost, n, imprint, threads)


def _check_inputs(ext, views, scale, G, column_cost, n: int) -> None:
    """Shapes, devices and ranges the kernel relies on (it reads raw pointers: a wrong one would crash)."""
    for name, t in (("ext", ext), ("views", views), ("scale", scale), ("G", G), ("column_cost", column_cost)):
        if not isinstance(t, torch.Tensor) or t.device.type != "cpu":
            raise ValueError(f"the fused carving takes CPU tensors; {name} is "
                             f"{t.device if isinstance(t, torch.Tensor) else type(t).__name__}")
    if ext.dim() != 3 or views.dim() != 2:
        raise ValueError(f"ext must be (K, Hp, Wp) and views (B, V), got {tuple(ext.shape)} and {tuple(views.shape)}")
    B, V = views.shape
    K, Hp, Wp = ext.shape
    if V > MAX_VIEWS:
        raise ValueError(f"the fused carving takes at most {MAX_VIEWS} view slots, got {V}")
    if not 1 <= n <= MAX_RESOLUTION:
        raise ValueError(f"the fused carving takes resolutions 1 to {MAX_RESOLUTION}, got {n}")
    if Hp * Wp >= 2 ** 31 - Wp:
        raise ValueError(f"maps of {Hp} x {Wp} pixels are too large for the fused carving's 32-bit offsets")
    if tuple(scale.shape) != (B, V) or tuple(G.shape) != (B, V, 2, 4) or tuple(column_cost.shape) != (B, n * n):
        raise ValueError(f"scale, G, column_cost must be ({B}, {V}), ({B}, {V}, 2, 4), ({B}, {n * n}); got "
                         f"{tuple(scale.shape)}, {tuple(G.shape)}, {tuple(column_cost.shape)}")
    if views.numel() and (int(views.max()) >= K or int(views.min()) < -1):
        raise ValueError(f"views must index the {K} maps of ext, or be -1 (unused), got "
                         f"{int(views.min())} .. {int(views.max())}")


def _carve_with(lib, fused: bool, ext, views, scale, G, column_cost, n: int, imprint: bool, threads):
    B, V = views.shape
    ext = ext.to(torch.float32).contiguous()
    views = views.to(torch.int64).contiguous()
    if views.numel() and int(views.max()) >= ext.shape[0] - 1:
        # the kernel may read one pixel past the last map it samples (with weight 0): give it one
        # (CarveMaps never needs this: its last map is the unused-slot one, which is never sampled)
        ext = _padded(ext)
    scale = scale.to(torch.float32).contiguous()
    G = G.to(torch.float32).contiguous()
    column_cost = column_cost.to(torch.float32).contiguous()
    HW = n * n
    occ = torch.zeros(B, n, HW, dtype=torch.uint8)
    columns = torch.zeros(B, HW, dtype=torch.uint8)
    nonempty = torch.zeros(B, dtype=torch.uint8)
    samples = torch.zeros(B, dtype=torch.int64)
    fn = lib.carvi_carve_fma if fused else lib.carvi_carve_plain
    args = (_ptr(ext), ext.shape[1], ext.shape[2], _ptr(views), _ptr(scale), _ptr(G), _ptr(column_cost), V, n,
            int(bool(imprint)))
    outs = (_ptr(occ), _ptr(columns), _ptr(nonempty), _ptr(samples))
    threads = max(1, torch.get_num_threads() if threads is None else int(threads))
    weights = ((column_cost < 0).sum(1) * ((views >= 0).sum(1) + 1)).tolist()
    # a few ranges per thread, taken in turn by the threads as they finish: the weights only
    # estimate the work (interior voxels cost every view, exterior ones about one)
    ranges = [r for r in _ranges(weights, threads * _RANGES_PER_THREAD if threads > 1 else 1) if r[1] > r[0]]

    def run(r):
        return fn(*args, r[0], r[1], *outs)

    if threads == 1 or len(ranges) == 1:
        codes = [run(r) for r in ranges]
    else:
        codes = list(_pool(threads).map(run, ranges))
    if any(c != 0 for c in codes):
        what = {-1: "too many view slots or a resolution out of range", -2: "out of memory"}
        raise RuntimeError("the fused carving kernel failed: "
                           + ", ".join(sorted({what.get(c, f"code {c}") for c in codes if c != 0})))
    return occ.view(torch.bool), columns.view(torch.bool), nonempty.view(torch.bool), samples
