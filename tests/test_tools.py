"""The benchmark tools run, and what they report is consistent (a small class; seconds, not minutes)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

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
    for name in ("batched", "batched_nearest"):
        r = cs["over_its_floor_within_runs"][name]
        assert r["min"] <= r["median"] <= r["max"] < float("inf"), (name, r)
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
    """tools/bench_malloc.py: both carving set-ups run in child processes under both malloc settings,
    and the report holds what each child measured."""
    out = tmp_path / "malloc.json"
    cmd = [sys.executable, str(ROOT / "tools" / "bench_malloc.py"), "--data", str(small_class),
           "--objects", "2", "--threads", "1", "--calls", "1", "--rounds", "1",
           "--work-dir", str(tmp_path / "work"), "--out", str(out)]
    res = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    r = json.loads(out.read_text())
    for kind in ("carve", "carve_loaded"):
        assert len(r[kind]["rounds"]) == 1
        for rnd in r[kind]["rounds"]:
            for setting in ("false", "true"):
                m = rnd[setting]
                assert m["objects"] == 2 and m["threads"] == 1 and m["seconds_per_object"] > 0
                assert m["faults_per_object"] >= 0
        s = r[kind]["seconds_per_object"]
        assert s["adaptive_over_fixed_min"] <= s["adaptive_over_fixed_median"] <= s["adaptive_over_fixed_max"]
    assert "e2e" not in r  # only with --e2e (the whole pipeline twice: minutes on the benchmark's class)


def test_sample_bounds_of_a_coarse_to_fine_carving(small_class: Path, tmp_path: Path):
    """tools/carve_sample_bounds.py: fractions of the dense samples, the per-view bounds never needing
    more than the single bound, and every imprinted column among those sampled whole."""
    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import carve_sample_bounds
    finally:
        sys.path.remove(str(ROOT / "tools"))
    r = carve_sample_bounds.main(["--data", str(small_class), "--objects", "2", "--blocks", "2", "4",
                                  "--out", str(tmp_path / "bounds.json")])
    assert r["proposals"] > 0 and len(r["rows"]) == 4
    rows = {(x["block"], x["per_view_bounds"]): x for x in r["rows"]}
    for (block, per_view), x in rows.items():
        assert 0 < x["sample_fraction"] <= 1.0 + 1e-9, x
        assert x["imprinted_column_fraction"] <= x["candidate_column_fraction"] <= 1, x
        if per_view:
            assert x["sample_fraction"] <= rows[(block, False)]["sample_fraction"] + 1e-12
    # sampling every second depth needs at least half of the samples, and more than the sampled depths
    assert rows[(2, True)]["sample_fraction"] >= 31 / 60
