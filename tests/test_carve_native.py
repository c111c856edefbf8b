"""Tests of carvi_torch.carve.native: the compiled CPU carving kernel and the ``backend`` choice.

References: ``torch.nn.functional.grid_sample`` (the kernel's bilinear sample, bit for bit), the
torch backend of :func:`carvi_torch.carve.carve_proposals` and the per-proposal loop (labels
voxel for voxel, on random blobs and on the real PASCAL VOC aeroplanes), a count of the samples
dense carving reads (the kernel must read fewer). The kernel is built with the machine's C
compiler; where none works, the tests that need it skip and say why (``backend="auto"`` then
runs torch, which the fallback test checks in a child process).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from carvi_torch.carve import carve_proposals, carve_proposals_loop, prepare_maps
from carvi_torch.carve import native as carve_fused
from carvi_torch.carve.torch_backend import grid_sample_maps, kernel_inputs
from carvi_torch.config import Config, ConfigError
from carvi_torch.sdf import signed_distance
from test_carve import blob_masks, random_cameras, random_proposals

ROOT = Path(__file__).resolve().parents[1]

needs_kernel = pytest.mark.skipif(not carve_fused.available(),
                                  reason=f"fused kernel unavailable: {carve_fused.unavailable_reason()}")


def _reference(ext, k, scale, grid):
    """``grid_sample`` of map ``k`` scaled, as the torch carving calls it."""
    return grid_sample_maps((ext[k] * scale)[None, None], grid.view(1, 1, -1, 2)).view(-1)


def _kernel_inputs(seed: int, n: int, **kw):
    """What :func:`carve_fused.carve_labels` takes, for random proposals (``random_proposals(**kw)``)."""
    gen = torch.Generator().manual_seed(seed)
    sdf, cams, reference, views = random_proposals(gen, **kw)
    return kernel_inputs(prepare_maps(sdf, cams), reference, views, n)[:5]


# --------------------------------------------------------------------------- sample


@needs_kernel
@pytest.mark.parametrize("size", [(2, 2), (5, 9), (64, 48), (161, 143)])
def test_sample_equals_grid_sample_bit_for_bit(size):
    gen = torch.Generator().manual_seed(sum(size))
    H, W = size
    ext = torch.randn(3, H, W, generator=gen) * 30
    ext[2] = torch.randn(H, W, generator=gen) * 1e6  # large values, as empty masks' maps hold
    grid = torch.rand(50000, 2, generator=gen) * 2.6 - 1.3  # inside, on and beyond the border
    grid[:2000] = torch.round(grid[:2000] * 16) / 16  # pixel centres, edges and the border itself
    grid[2000:2010] = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [0.0, 0.0],
                                    [1.0, 0.3], [0.3, 1.0], [-1.0, 0.3], [1.5, 1.5], [-1.5, -1.5]])
    for k in range(3):
        for scale in (1.0, 0.37, 2.9):
            got, want = carve_fused.sample(ext, k, scale, grid), _reference(ext, k, scale, grid)
            assert torch.equal(got, want), (k, scale, int((got != want).sum()))


@needs_kernel
def test_sample_shapes_and_known_values():
    ext = torch.tensor([[[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]])  # (1, 2, 3)
    grid = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.0], [0.0, -1.0], [5.0, 5.0]])
    out = carve_fused.sample(ext, 0, 2.0, grid)
    assert out.shape == (5,) and out.dtype == torch.float32
    # corners, the centre (mean of the four middle pixels' bilinear mix), an edge midpoint, border
    assert out.tolist() == pytest.approx([0.0, 10.0, 5.0, 2.0, 10.0])


def test_variant_is_known():
    assert carve_fused.variant() in ({"fma", "plain"} if carve_fused.available() else {None})
    assert (carve_fused.unavailable_reason() is None) == carve_fused.available()


# --------------------------------------------------------------------------- labels


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


@needs_kernel
def test_fused_labels_on_steep_maps_and_many_proposals():
    """Maps that are not distance maps (steep noise), many views, odd sizes: still the torch labels."""
    for seed in range(3):
        gen = torch.Generator().manual_seed(40 + seed)
        sdf, cams, reference, views = random_proposals(gen, M=10, B=24, V=7, size=27)
        sdf = sdf + 4.0 * torch.randn(sdf.shape, generator=gen)
        for imprint in (True, False):
            a = carve_proposals(sdf, cams, reference, views, resolution=17, imprint=imprint, backend="torch")
            b = carve_proposals(sdf, cams, reference, views, resolution=17, imprint=imprint, backend="fused")
            assert torch.equal(a.occupancy, b.occupancy) and torch.equal(a.columns, b.columns)
            assert torch.equal(a.empty, b.empty)


@needs_kernel
def test_fused_reads_fewer_samples_than_dense_carving():
    n = 20
    ext, slots, scale, G, column_cost = _kernel_inputs(3, n, M=8, B=16, V=4, size=32)
    occ, columns, nonempty, samples = carve_fused.carve_labels(ext, slots, scale, G, column_cost, n, imprint=False)
    fg = (column_cost < 0).sum(1)
    dense = fg * (slots >= 0).sum(1) * n  # what the torch backend samples: every view at every foreground voxel
    interior = occ.flatten(1).sum(1)
    used = (slots >= 0).sum(1)
    assert (samples <= dense).all() and samples.sum() < 0.9 * dense.sum()
    # an interior voxel needs every view; an exterior foreground voxel at least one (when there is a view)
    assert (samples >= interior * used + (fg * n - interior) * (used > 0)).all()
    assert torch.equal(nonempty, occ.flatten(1).any(1)) and torch.equal(columns, occ.any(1))


@needs_kernel
@pytest.mark.parametrize("threads", [1, 2, 5])
def test_threads_do_not_change_the_labels(threads):
    n = 15
    ext, slots, scale, G, cc = _kernel_inputs(11, n, M=8, B=13, V=4, size=32)
    one = carve_fused.carve_labels(ext, slots, scale, G, cc, n, True, threads=1)
    many = carve_fused.carve_labels(ext, slots, scale, G, cc, n, True, threads=threads)
    for a, b in zip(one, many):
        assert torch.equal(a, b)


def test_ranges_split_by_weight():
    r = carve_fused._ranges([5, 1, 1, 1, 1, 1, 5], 2)
    assert r[0][0] == 0 and r[-1][1] == 7 and all(a[1] == b[0] for a, b in zip(r, r[1:]))
    assert carve_fused._ranges([3, 3], 1) == [(0, 2)] and carve_fused._ranges([0, 0], 4) == [(0, 2)]
    assert len(carve_fused._ranges([1] * 10, 3)) == 3


@needs_kernel
def test_real_aeroplanes_fused_equals_torch(shared_data, tmp_path):
    """The pipeline's own proposals on the real PASCAL VOC aeroplanes: the same labels either way."""
    from carvi_torch import pipeline
    from carvi_torch.io import coco
    from carvi_torch.io.voc import convert

    ann = tmp_path / "aeroplane.json"
    convert(shared_data / "pascal_voc_aeroplane" / "keypoints", ann)
    cfg = Config().override(dict(data=str(ann), progress=False))
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


# --------------------------------------------------------------------------- backend choice


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


def test_without_a_compiler_auto_runs_torch_and_fused_says_why(tmp_path):
    """A machine with no working C compiler: the kernel is unavailable with the reason, ``auto``
    carves with torch (same labels), ``fused`` is refused, in a fresh process and cache."""
    code = """
import json, torch
from carvi_torch.carve import native as carve_fused
from carvi_torch.carve import carve_proposals
from test_carve import random_proposals
sdf, cams, ref, views = random_proposals(torch.Generator().manual_seed(6))
a = carve_proposals(sdf, cams, ref, views, resolution=10, backend="auto")
b = carve_proposals(sdf, cams, ref, views, resolution=10, backend="torch")
try:
    carve_proposals(sdf, cams, ref, views, resolution=10, backend="fused")
    refused = None
except ValueError as exc:
    refused = str(exc)
print(json.dumps(dict(available=carve_fused.available(), reason=carve_fused.unavailable_reason(),
                      same=bool(torch.equal(a.occupancy, b.occupancy)), refused=refused)))
"""
    env = dict(os.environ, CC=str(tmp_path / "no-such-compiler"), CARVI_TORCH_CACHE=str(tmp_path / "cache"),
               PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "tests")]))
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["available"] is False and "no-such-compiler" in res["reason"]
    assert res["same"] is True
    assert "not available here" in res["refused"] and "no-such-compiler" in res["refused"]
    assert not list((tmp_path / "cache").rglob("*.so"))  # nothing half-built left behind


@needs_kernel
def test_the_build_is_cached_and_reused(tmp_path):
    """A fresh cache builds the library once; a second process loads it without rebuilding."""
    code = ("import json; from carvi_torch.carve import native as f; ok = f.available(); "
            "p = f.library_path(); print(json.dumps([ok, str(p), p.stat().st_mtime_ns]))")
    env = dict(os.environ, CARVI_TORCH_CACHE=str(tmp_path), PYTHONPATH=str(ROOT))
    runs = [json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      timeout=300, check=True).stdout.strip().splitlines()[-1]) for _ in range(2)]
    assert runs[0][0] and runs[1][0]
    assert runs[0][1] == runs[1][1] and Path(runs[0][1]).parent.parent == tmp_path
    assert runs[0][2] == runs[1][2]  # not rebuilt
    assert len(list(tmp_path.rglob("*.so"))) == 1


def test_a_kernel_that_disagrees_with_grid_sample_is_not_used(monkeypatch):
    """The loader's self-test rejects a sample that differs from grid_sample in the last bit."""
    if not carve_fused.available():
        pytest.skip(f"fused kernel unavailable: {carve_fused.unavailable_reason()}")
    lib = carve_fused._state["lib"]
    real = carve_fused._sample_with

    def off_by_an_ulp(lib_, fused, ext, k, scale, grid):
        out = real(lib_, fused, ext, k, scale, grid)
        out[7] = torch.nextafter(out[7], torch.tensor(float("inf")))
        return out

    monkeypatch.setattr(carve_fused, "_sample_with", off_by_an_ulp)
    assert carve_fused._self_test(lib) is None
    monkeypatch.setattr(carve_fused, "_sample_with", real)
    assert carve_fused._self_test(lib) == carve_fused.variant()
    # the same for the column sampler the carving uses
    real_line = carve_fused._line_with

    def line_off(lib_, fused, ext, k, scale, g0, c, m):
        out = real_line(lib_, fused, ext, k, scale, g0, c, m)
        out[-1] = torch.nextafter(out[-1], torch.tensor(float("-inf")))
        return out

    monkeypatch.setattr(carve_fused, "_line_with", line_off)
    assert carve_fused._self_test(lib) is None


@needs_kernel
def test_both_variants_carve_and_differ_only_at_the_zero_level():
    """The variant the self-test did not pick still carves: without imprinting its labels differ from the
    chosen one's only where the cost is within float rounding of 0 (a thin set, here none); with imprinting
    the same columns are filled, though an imprinted voxel may move along a column of near-equal costs."""
    n = 18
    ext, slots, scale, G, cc = _kernel_inputs(21, n, M=8, B=16, V=4, size=32)
    other_name = "plain" if carve_fused.variant() == "fma" else "fma"
    if other_name == "fma" and not carve_fused._state["lib"].carvi_has_fma():
        pytest.skip("this processor has no FMA: only the plain variant runs here")
    for imprint in (False, True):
        chosen = carve_fused.carve_labels(ext, slots, scale, G, cc, n, imprint)
        other = carve_fused.carve_labels(ext, slots, scale, G, cc, n, imprint, variant=other_name)
        assert torch.equal(chosen[1], other[1]) and torch.equal(chosen[2], other[2])
        if not imprint:
            differ = (chosen[0] != other[0]).float().mean().item()
            assert differ < 1e-3, differ
    with pytest.raises(ValueError, match="variant"):
        carve_fused.carve_labels(ext, slots, scale, G, cc, n, True, variant="avx512")


@needs_kernel
def test_a_view_of_the_last_map_is_read_safely():
    """When a view samples the last map of ``ext`` (never in a CarveMaps, whose last map is the unused
    slot's), the kernel gets a copy with a value after it: the labels equal those with a spare map."""
    n = 14
    ext, slots, scale, G, cc = _kernel_inputs(8, n)
    last = ext.shape[0] - 1
    slots = slots.clone()
    slots[:, 0] = torch.where(slots[:, 0] >= 0, torch.full_like(slots[:, 0], last), slots[:, 0])
    ext = ext.clone()
    ext[last] = ext[0]  # a real map in the last row
    a = carve_fused.carve_labels(ext, slots, scale, G, cc, n, True)
    spare = torch.cat([ext, torch.zeros_like(ext[:1])])  # the same maps with one more after them
    b = carve_fused.carve_labels(spare, slots, scale, G, cc, n, True)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


@needs_kernel
def test_carve_labels_checks_its_inputs():
    n = 10
    ext, slots, scale, G, cc = _kernel_inputs(9, n)
    with pytest.raises(ValueError, match="views must index"):
        carve_fused.carve_labels(ext, torch.full_like(slots, ext.shape[0]), scale, G, cc, n, True)
    with pytest.raises(ValueError, match="scale, G, column_cost"):
        carve_fused.carve_labels(ext, slots, scale, G, cc[:, :-1], n, True)
    with pytest.raises(ValueError, match="resolutions"):
        carve_fused.carve_labels(ext, slots, scale, G, cc, 0, True)
    with pytest.raises(ValueError, match="view slots"):
        many = torch.full((slots.shape[0], 65), -1)
        carve_fused.carve_labels(ext, many, torch.ones(slots.shape[0], 65), torch.zeros(slots.shape[0], 65, 2, 4), cc,
                                 n, True)


def test_more_view_slots_than_the_kernel_takes_run_on_torch():
    gen = torch.Generator().manual_seed(12)
    sdf, cams, reference, views = random_proposals(gen, M=8, B=8, V=4, size=24)
    wide = torch.full((8, 70), -1)
    wide[:, :4] = views
    a = carve_proposals(sdf, cams, reference, wide, resolution=10, backend="auto")
    b = carve_proposals(sdf, cams, reference, views, resolution=10, backend="torch")
    assert torch.equal(a.occupancy, b.occupancy)
    if carve_fused.available():
        with pytest.raises(ValueError, match="view slots"):
            carve_proposals(sdf, cams, reference, wide, resolution=10, backend="fused")


def _carve_in_forked_child(queue, args):
    queue.put([t.numpy().copy() for t in carve_fused.carve_labels(*args, threads=2)])  # by value, not shared


@needs_kernel
def test_a_forked_child_carves_with_threads():
    """A child forked after the parent's thread pool started must not wait for threads it does not have."""
    import multiprocessing as mp

    n = 12
    args = (*_kernel_inputs(10, n), n, True)
    want = carve_fused.carve_labels(*args, threads=2)  # the parent's pool now exists
    ctx = mp.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_carve_in_forked_child, args=(queue, args))
    child.start()
    got = queue.get(timeout=60)
    child.join(timeout=60)
    assert child.exitcode == 0
    for x, y in zip(want, got):
        assert torch.equal(x, torch.from_numpy(y))


@needs_kernel
def test_the_portable_build_carves_like_the_x86_one(tmp_path):
    """The code for processors without AVX2 (``CARVI_NO_X86``: what aarch64 builds) compiles and gives the
    plain variant's labels."""
    import ctypes

    path = tmp_path / "portable.so"
    carve_fused._build(path, ("-DCARVI_NO_X86",))
    lib = ctypes.CDLL(str(path))
    carve_fused._declare(lib)
    n = 13
    ext, slots, scale, G, cc = _kernel_inputs(14, n)
    want = carve_fused.carve_labels(ext, slots, scale, G, cc, n, True, variant="plain")
    got = carve_fused._carve_with(lib, False, ext, slots, scale, G, cc, n, True, 1)
    for x, y in zip(want, got):
        assert torch.equal(x, y)


def test_the_kernel_takes_every_resolution_carve_proposals_takes():
    from carvi_torch.carve.geometry import check_indices
    with pytest.raises(ValueError, match="2048"):
        check_indices(2, torch.tensor([0]), torch.tensor([[1]]), 2049, torch.device("cpu"))
    assert carve_fused.MAX_RESOLUTION >= 2048
