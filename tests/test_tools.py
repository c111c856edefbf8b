"""The benchmark tools run, and what they report is consistent (a small class; seconds, not minutes)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_carving_comparison_on_a_small_class(tmp_path: Path):
    out = tmp_path / "bench.json"
    cmd = [sys.executable, str(ROOT / "tools" / "benchmark.py"), "--objects", "30", "--carve-objects", "3",
           "--loop-objects", "1", "--repeat", "2", "--skip-e2e", "--threads", "1",
           "--data-dir", str(tmp_path / "data"), "--work-dir", str(tmp_path / "runs"), "--out", str(out)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    cs = json.loads(out.read_text())["carving"]
    # every exact variant and every loop agrees with the batched carving voxel for voxel, and both
    # nearest-pixel loops (the timed reference structure among them) with the nearest-pixel batched carving
    assert cs["identical"] and all(cs["identical"].values()), cs["identical"]
    assert "loop_reference_structure_nearest_vs_batched_nearest" in cs["identical"]
    s = cs["seconds_per_object"]
    for key in ("batched", "batched_nearest", "loop_reference_structure", "loop_reference_structure_nearest",
                "floor_batched", "floor_batched_nearest", "floor_loop_naive", "floor_loop_naive_nearest"):
        assert s[key] > 0, key
    fused = cs["carve_backend"] == "fused"  # the pipeline's default on the CPU where the kernel builds
    for name in ("batched_torch" if fused else "batched", "batched_nearest"):
        r = cs["over_its_floor_within_runs"][name]
        assert r["min"] <= r["median"] <= r["max"] < float("inf"), (name, r)
    for name in ("batched", "batched_nearest") + (("batched_torch",) if fused else ()):
        # the paired rounds' ratios are ordered and finite, the loop slower than the batched carving
        # in the median round (10x on 50 objects; here 3 objects against 1, so only > 1)
        w = cs["speedup_vs_loop_reference_structure_within_rounds"][name]
        assert 0 < w["min"] <= w["median"] <= w["max"] < float("inf"), (name, w)
        assert w["median"] > 1, (name, w)
    # a nearest-pixel sample is several times cheaper than a bilinear one (3x on the development
    # machine): both floors, the batched carving's and the naive loop's, must show it
    assert s["floor_batched_nearest"] < s["floor_batched"]
    assert s["floor_loop_naive_nearest"] < s["floor_loop_naive"]
    # the nearest carving samples the same voxels as the bilinear one (up to the columns whose
    # reference sign differs), and the batched carvings sample fewer voxels than the naive loop
    sm = cs["samples_per_object"]
    assert abs(sm["batched_nearest"] - sm["batched"]) <= 0.02 * sm["batched"]
    assert sm["batched"] < sm["loop_naive"] < sm["loop_reference_structure"]
    if fused:
        # the floor of the fused carving is the torch backend's grid_sample calls; the kernel's early
        # exit reads fewer samples than those
        assert s["floor_batched"] == s["floor_batched_torch"] and sm["batched"] == sm["batched_torch"]
        assert 0 < cs["fused_samples_per_object"] < sm["batched"]
        assert cs["fused_kernel_variant"] in ("fma", "plain") and cs["fused_over_torch"] > 0
    assert (out.with_suffix(".md")).is_file()


def test_carving_figure_from_the_kept_runs(tmp_path: Path):
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import figure_carving
    finally:
        sys.path.remove(str(ROOT / "tools"))
    runs = figure_carving.DEFAULT_RUNS
    out = figure_carving.main(["--runs", *map(str, runs), "--out", str(tmp_path / "fig.png")])
    assert out.is_file() and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 20_000
    with pytest.raises(SystemExit, match="benchmark JSON not found"):
        figure_carving.main(["--runs", str(tmp_path / "missing.json"), "--out", str(tmp_path / "x.png")])


@pytest.fixture(scope="module")
def small_class(tmp_path_factory) -> Path:
    """annotations.json of 12 procedural cars."""
    from carvi_torch.synthetic import procedural

    data = tmp_path_factory.mktemp("small_class")
    procedural.write_default_collection(data, instances_per_class=12, categories=["car"], seed=0, progress=False)
    return data / "annotations.json"


def test_malloc_threshold_comparison_on_a_small_class(small_class: Path, tmp_path: Path):
    """tools/bench_malloc.py: both carving set-ups run in child processes under both malloc settings (the
    fixed children see the thresholds, the adaptive ones none, whatever the caller set), and the report
    holds what each child measured."""
    out = tmp_path / "malloc.json"
    cmd = [sys.executable, str(ROOT / "tools" / "bench_malloc.py"), "--data", str(small_class),
           "--objects", "2", "--threads", "1", "--calls", "1", "--rounds", "1",
           "--work-dir", str(tmp_path / "work"), "--out", str(out)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, OMP_NUM_THREADS="1", MALLOC_TRIM_THRESHOLD_="4096"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    r = json.loads(out.read_text())
    fixed = {"MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(256 << 20)}
    for kind in ("carve", "carve_loaded"):
        rounds = r[kind]["rounds"]
        assert [list(x) for x in rounds] == [["adaptive", "fixed"]]  # the first round's order
        for rnd in rounds:
            assert rnd["fixed"]["environment"] == fixed
            assert rnd["adaptive"]["environment"] == {k: None for k in fixed}
            for m in rnd.values():
                assert m["objects"] == 2 and m["threads"] == 1 and m["seconds_per_object"] > 0
        s = r[kind]["seconds_per_object"]
        ratios = sorted(x["adaptive"]["seconds_per_object"] / x["fixed"]["seconds_per_object"] for x in rounds)
        assert s["adaptive_over_fixed_min"] == ratios[0] and s["adaptive_over_fixed_max"] == ratios[-1]
    assert "e2e" not in r  # only with --e2e (the whole pipeline twice: minutes on the benchmark's class)


def _tool(name: str):
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(ROOT / "tools"))


def test_sample_bounds_of_a_coarse_to_fine_carving(small_class: Path, tmp_path: Path):
    """tools/carve_sample_bounds.py: sound bounds (no decision the exact costs contradict), fractions
    of the dense samples, and the per-view bounds never needing more than the single bound."""
    r = _tool("carve_sample_bounds").main(["--data", str(small_class), "--objects", "2", "--blocks", "2", "4",
                                           "--out", str(tmp_path / "bounds.json")])
    assert r["proposals"] > 0 and len(r["rows"]) == 4
    rows = {(x["block"], x["per_view_bounds"]): x for x in r["rows"]}
    for (block, per_view), x in rows.items():
        assert x["violations"] == 0, x
        assert 0 < x["sample_fraction"] <= 1.0 + 1e-9, x
        assert x["imprinted_column_fraction"] <= x["candidate_column_fraction"] <= 1, x
        if per_view:
            assert x["sample_fraction"] <= rows[(block, False)]["sample_fraction"] + 1e-12
    # sampling every second depth needs at least half of the samples, and more than the sampled depths
    assert rows[(2, True)]["sample_fraction"] >= 31 / 60


def test_sample_bounds_simulation_counts_violations_of_a_bound_too_small():
    """The simulation's soundness count can fail: a quarter of a valid bound contradicts the costs."""
    tool = _tool("carve_sample_bounds")
    depth = torch.arange(60, dtype=torch.float64)
    # one view, one column: the cost falls 1 per step to -20 at depth 30, then rises again
    S = (depth - 30).abs()[None, :, None] - 20.0
    assert tool.simulate(S, torch.tensor([1.0 + 1e-3]), 6, True)["violations"] == 0
    assert tool.simulate(S, torch.tensor([0.25]), 6, True)["violations"] > 0


@pytest.mark.parametrize("block", [3, 4, 7])
@pytest.mark.parametrize("imprint", [True, False])
def test_depth_block_prototype_equals_the_batched_carving(small_class: Path, block: int, imprint: bool):
    """The prototype the tool times gives the batched carving's labels voxel for voxel (small chunks,
    so that chunks hold padding columns)."""
    import argparse

    from carvi_torch import carve as C

    tool = _tool("carve_sample_bounds")
    ns = argparse.Namespace(data=str(small_class), category="car", objects=3)
    cfg, plan, _, K, ref, views, _ = _tool("bench_changes").class_proposals(ns, torch.device("cpu"))
    want = C.carve_proposals(plan.maps, None, ref, views, resolution=cfg.resolution, imprint=imprint,
                             max_batch_voxels=20_000).occupancy
    got = tool.carve_blocks(plan.maps, ref, views, cfg.resolution, block, imprint, max_batch_voxels=20_000)
    assert want.any() and torch.equal(got, want)


def test_gpu_session_keeps_the_callers_python_path(tmp_path: Path):
    """The GPU script adds the checkout to PYTHONPATH without dropping what the caller put there
    (a lent machine's carried packages); without CUDA it stops with status 2 and says why."""
    log = tmp_path / "pythonpath.txt"
    fake = tmp_path / "fakepython"
    # records the path it was started with, then fails every check (no packages, no CUDA)
    fake.write_text(f'#!/bin/sh\necho "$PYTHONPATH" >> "{log}"\nexit 1\n')
    fake.chmod(0o755)
    work = tmp_path / "work"  # no .whl/ here: the script takes the branch without wheels
    work.mkdir()
    env = dict(os.environ, PYTHON=str(fake), PYTHONPATH="/carried/site")
    script = ROOT / "tools" / "gpu_session.sh"
    proc = subprocess.run(["bash", str(script), "tests", str(tmp_path / "out")], cwd=work, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert "no CUDA device" in proc.stderr
    seen = log.read_text().split()
    assert len(seen) == 2  # the package check, then the CUDA check
    assert seen[1].split(":") == [str(work), "/carried/site"]
