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

Building and caching: :mod:`carvi_torch.native_library` (one library for the package's kernels, built on
first use with the machine's C++ compiler, cached per user under ``$CARVI_TORCH_CACHE/kernels``). No
compiler, a failed build or a failed self-test makes :func:`available` ``False`` with the reason in
:func:`unavailable_reason`; nothing else changes.

Threads. The operator carves in torch's intra-op thread pool (``at::parallel_for``), so
``torch.set_num_threads`` governs it; its threads take proposals one at a time, heaviest first. The
dispatcher releases the GIL during the call. No fork handling: a forked child is in the state of
every torch operator there (with GNU OpenMP, a child that runs a parallel region after its parent
ran one waits forever, whichever operator it is, unless it sets ``torch.set_num_threads(1)``).

The same library holds the rigid SfM's factorisation loop (``kernels/sfm_steps.h``, operator ``sfm_factorize``,
used by :mod:`carvi_torch.viewpoints.sfm` through :func:`carvi_torch.native_library.library_operators`): it
samples no maps, so the self-test does not concern it.

NaN. A NaN sample does not win the kernel's maximum, while ``torch.maximum`` propagates it; the
carving never sees one (the maps and the cameras are checked finite).

Example:
    >>> isinstance(available(), bool)
    True
"""
from __future__ import annotations

from types import SimpleNamespace

import torch

from .. import native_library
from ..cameras import ScaledOrthographic, random_rotations
from ..native_library import cache_entry_problem, library_path
from .geometry import prepare_maps
from .torch_backend import carve_torch, grid_sample_maps, kernel_inputs, sample_planes


__all__ = ["available", "unavailable_reason", "carve_labels", "sample", "variant", "library_path", "status",
           "operators", "cache_entry_problem", "MAX_VIEWS", "MAX_RESOLUTION"]
#: Largest resolution the kernel takes (``CARVI_MAX_RESOLUTION`` in the C++ source).
MAX_RESOLUTION = 2048
#: Most view slots a proposal may use (``CARVI_MAX_VIEWS`` in the C++ source).
MAX_VIEWS = 64

_state: dict = {}


def _checked(state: dict) -> None:
    """The library's operators and the variant whose samples pass the self-test, into ``state``."""
    lib = native_library.load()
    try:
        ops, path, rebuilt = lib["ops"], lib["path"], lib["rebuilt"]
        if ops is None:
            raise RuntimeError(lib["reason"])
        name = _self_test(ops)
        if name is None:
            raise RuntimeError("the kernel's bilinear samples differ from torch's grid_sample on this machine "
                               f"(CPU capability {torch.backends.cpu.get_cpu_capability()}), so its labels "
                               "could differ from the torch carving's")
        state.update(ops=ops, variant=name, reason=None, path=path, rebuilt=rebuilt)
    except Exception as exc:  # noqa: BLE001 -- whatever fails, the torch carving runs instead
        state.update(ops=None, variant=None, reason=f"{type(exc).__name__}: {exc}", path=None, rebuilt=None)


def _load() -> dict:
    return native_library.once(_state, _checked)


def operators():
    """The loaded operators (``torch.ops.<namespace>``: ``carve_labels``, ``sample``, ``line``, ``has_fma``),
    or ``None`` where the kernel is not available."""
    return _load()["ops"]


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
