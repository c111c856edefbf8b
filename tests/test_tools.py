"""The benchmark tools run, and what they report is consistent (a small class; seconds, not minutes)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import load_tool, run_each_in_a_fresh_process

ROOT = Path(__file__).resolve().parents[1]


def test_benchmark_carving_comparison_on_a_small_class(tmp_path: Path):
    """The carving comparison runs every variant on a small class and checks them against each other:
    voxel identity and sample counts (deterministic); its timings are reported, never asserted. The
    record goes under ``--key`` of ``--out``, whose other records stay as they were."""
    out = tmp_path / "bench.json"
    out.write_text(json.dumps({"older": {"command": "kept"}}))
    script = str(ROOT / "tools" / "benchmark.py")
    argv = [script, "--objects", "20", "--carve-objects", "2",
            "--loop-objects", "1", "--repeat", "1", "--skip-e2e", "--threads", "1", "--resolution", "32",
            "--proposals", "8", "--data-dir", str(tmp_path / "data"), "--work-dir", str(tmp_path / "runs"),
            "--out", str(out), "--key", "small"]
    # `python tools/benchmark.py ...` in a fresh process, on one torch thread (as OMP_NUM_THREADS=1 would run it)
    code = (f"import runpy, sys, torch; torch.set_num_threads(1); sys.argv = {argv!r}; "
            f"runpy.run_path({script!r}, run_name='__main__')")
    [(rc, stdout, stderr)] = run_each_in_a_fresh_process([code], cwd=ROOT, env=dict(os.environ, OMP_NUM_THREADS="1"))
    res = subprocess.CompletedProcess(argv, rc, stdout, stderr)
    assert res.returncode == 0, res.stdout[-2000:] + res.stderr[-2000:]
    records = json.loads(out.read_text())
    assert sorted(records) == ["older", "small"] and records["older"] == {"command": "kept"}
    cs = records["small"]["carving"]
    # every exact variant and every loop agrees with the batched carving voxel for voxel, and both
    # nearest-pixel loops (the timed reference structure among them) with the nearest-pixel batched carving
    assert cs["identical"] and all(cs["identical"].values()), cs["identical"]
    assert "loop_reference_structure_nearest_vs_batched_nearest" in cs["identical"]
    s = cs["seconds_per_object"]
    for key in ("batched", "batched_nearest", "loop_reference_structure", "loop_reference_structure_nearest",
                "floor_batched", "floor_batched_nearest", "floor_loop_naive", "floor_loop_naive_nearest"):
        assert s[key] > 0, key
    fused = cs["carve_backend"] == "fused"  # the pipeline's default on the CPU where the kernel builds
    for name in ("batched", "batched_nearest") + (("batched_torch",) if fused else ()):
        w = cs["speedup_vs_loop_reference_structure_within_rounds"][name]
        assert 0 < w["min"] <= w["median"] <= w["max"] < float("inf"), (name, w)
    # the nearest carving samples the same voxels as the bilinear one (up to the columns whose
    # reference sign differs), and the batched carvings sample fewer voxels than the naive loop
    sm = cs["samples_per_object"]
    assert abs(sm["batched_nearest"] - sm["batched"]) <= 0.02 * sm["batched"]
    assert sm["batched"] < sm["loop_naive"] < sm["loop_reference_structure"]
    if fused:
        # the kernel's early exit reads fewer samples than the torch backend's grid_sample calls
        assert sm["batched"] == sm["batched_torch"]
        assert 0 < cs["fused_samples_per_object"] < sm["batched"]
        assert cs["fused_kernel_variant"] in ("fma", "plain") and cs["fused_over_torch"] > 0
    # the printed table: the variants as ratios to the default backend, and the label check
    assert "| / default |" in res.stdout and "| ratio (same run) | value |" in res.stdout
    assert "identical voxel for voxel: True" in res.stdout


def test_write_record_sets_one_key_and_keeps_the_rest(tmp_path: Path):
    """``write_record``: without a key the whole file; with one, that key of the file's object (a missing
    file starts empty, the other keys stay); a file that is not an object of records is refused."""
    from carvi_torch.io.outputs import write_record

    p = tmp_path / "records.json"
    write_record(p, {"a": 1}, "first")
    write_record(p, {"b": [2, 3]}, "second")
    write_record(p, {"a": 4}, "first")
    assert json.loads(p.read_text()) == {"first": {"a": 4}, "second": {"b": [2, 3]}}
    # one record per line, compact: a rewrite changes one line, the pages' files stay small
    assert p.read_text().splitlines() == ["{", '"first": {"a":4},', '"second": {"b":[2,3]}', "}"]
    whole = tmp_path / "whole.json"
    write_record(whole, [1, 2])
    assert json.loads(whole.read_text()) == [1, 2]
    with pytest.raises(ValueError, match="whole.json: not a JSON object of records"):
        write_record(whole, {"a": 1}, "k")
    assert json.loads(whole.read_text()) == [1, 2]


def test_benchmark_records_default_to_their_key_of_the_pages_file():
    """With neither ``--out`` nor ``--key`` the benchmark's record goes to its default key of
    outputs/benchmarks.json (a plain run leaves the committed records alone); ``--key`` alone names a key of
    docs/data/benchmarks.json (docs/benchmarks.md, whose commands name their key); ``--out`` alone is a file
    of its own."""
    bm = load_tool("benchmark", "benchmark_tool")
    import argparse

    import torch

    args = argparse.Namespace(out=None, key=None, skip_e2e=True, skip_carve=False, threads=2, objects=50)

    key = bm.default_key(torch.device("cpu"), args)
    assert key == "carving_cpu_threads2"
    assert bm.record_target(args, key) == (ROOT / "outputs" / "benchmarks.json", key)
    args.key = "meshing_cpu"
    assert bm.record_target(args, key) == (ROOT / "docs" / "data" / "benchmarks.json", "meshing_cpu")
    args.out, args.key = "x.json", None
    assert bm.record_target(args, key) == (Path("x.json"), None)
    args.skip_e2e = False
    assert bm.default_key(torch.device("cpu"), args) == "benchmark_cpu_50"
    # every key the pages name is in the file (the carving backends' speed is on the reconstruction page)
    pages = {p: (ROOT / "docs" / p).read_text() for p in ("benchmarks.md", "reconstruction.md")}
    records = json.loads((ROOT / "docs" / "data" / "benchmarks.json").read_text())
    for name, page in (("benchmark_cpu_1000", "benchmarks.md"), ("benchmark_cuda_9087_h100", "benchmarks.md"),
                       ("benchmark_cuda_9087_h200", "benchmarks.md"), ("many_classes_cpu", "benchmarks.md"),
                       ("meshing_cpu", "benchmarks.md"), ("many_classes_lean_writers", "benchmarks.md"),
                       ("benchmark_cuda_1000_h100", "reconstruction.md"), ("carving_cpu_threads1", "reconstruction.md"),
                       ("carving_cpu_threads2", "reconstruction.md")):
        assert f"`{name}`" in pages[page] and name in records, name


def test_plain_runs_of_the_record_tools_leave_docs_data_alone(tmp_path: Path):
    """bench_viewpoints, bench_export and voc_study write their records (and voc_study its figure) under
    outputs/ unless ``--out`` (or ``--key``, a key of the docs' file) names the destination."""
    import argparse

    bv, be, vs = load_tool("bench_viewpoints"), load_tool("bench_export"), load_tool("voc_study")
    docs = ROOT / "docs" / "data"
    plain, keyed, own = (argparse.Namespace(out=o, key=k) for o, k in ((None, None), (None, "k"), ("x.json", None)))
    assert bv._record_target(plain, "viewpoints_speed") == (ROOT / "outputs" / "viewpoints.json", "viewpoints_speed")
    assert bv._record_target(keyed, "viewpoints_speed") == (docs / "viewpoints.json", "k")
    assert bv._record_target(own, "viewpoints_speed") == (Path("x.json"), None)
    assert be._record_target(plain, "report.json", "report_160") == (ROOT / "outputs" / "report.json", "report_160")
    assert be._record_target(keyed, "export.json", "export") == (docs / "export.json", "k")
    args = vs.build_parser().parse_args([])
    assert vs.record_paths(args, tmp_path) == (tmp_path / "voc_study.json", tmp_path / "voc_aeroplanes.png")
    args = vs.build_parser().parse_args(["--out", str(docs / "voc_study.json"), "--figure", "none"])
    assert vs.record_paths(args, tmp_path) == (docs / "voc_study.json", None)


def test_docs_data_holds_few_records_each_named_by_a_page():
    """docs/data/ keeps raw JSON only where a page builds a table from it, at most 12 files: every file is
    linked from a page of docs/, and every link of a page into data/ names a file that is there."""
    import re

    data = ROOT / "docs" / "data"
    files = {p.name for p in data.glob("*.json")}
    assert 0 < len(files) <= 12, sorted(files)
    linked = set()
    for page in (ROOT / "docs").glob("*.md"):
        linked |= set(re.findall(r"\]\(data/([^)#]+\.json)\)", page.read_text()))
    assert linked <= files, sorted(linked - files)
    assert files <= linked, sorted(files - linked)


def test_many_class_cpu_clock_runs_keep_classes_sequential(tmp_path: Path):
    """``--cpu-clock`` runs the classes one after the other (a process's CPU time cannot be split between two
    threads' stages) where the compared code knows ``pipeline_classes``; wall-clock runs keep its default."""
    import argparse

    bench = load_tool("benchmark", "benchmark_tool")
    old = tmp_path / "old" / "carvi_torch"
    old.mkdir(parents=True)
    (old / "config.py").write_text("    report: bool = True\n")  # a checkout before pipeline_classes
    args = argparse.Namespace(device="cpu", set=["viewpoints.sfm_groups=1"], cpu_clock=True)
    cmd = bench.many_command(Path("d.json"), Path("o"), args, ["x=1"], None)
    assert cmd[1:3] == ["-c", bench.CPU_CLOCK] and cmd[-1] == "pipeline_classes=false"
    assert "viewpoints.sfm_groups=1" in cmd and "x=1" in cmd
    assert "pipeline_classes=false" not in bench.many_command(Path("d.json"), Path("o"), args, [], str(old.parent))
    args.cpu_clock = False
    wall = bench.many_command(Path("d.json"), Path("o"), args, [], None)
    assert wall[1:3] == ["-m", "carvi_torch.reconstruct"] and "pipeline_classes=false" not in wall


def test_many_class_child_keeps_the_inherited_pythonpath(tmp_path: Path, monkeypatch):
    """A compared run imports the code it names first and still finds dependencies installed outside the
    environment (a lent machine's private ``--target`` folder on the inherited ``PYTHONPATH``)."""
    import argparse

    bench = load_tool("benchmark", "benchmark_tool")
    seen = {}

    def fake_run(cmd, cwd, env, **kw):
        seen.update(env=env, cwd=cwd)
        raise RuntimeError("stop here")

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(["/deps/site", str(bench.ROOT)]))
    monkeypatch.setattr(bench.subprocess, "run", fake_run)
    (tmp_path / "old" / "carvi_torch").mkdir(parents=True)
    (tmp_path / "old" / "carvi_torch" / "config.py").write_text("    report: bool = True\n")
    args = argparse.Namespace(device="cpu", set=[], cpu_clock=False, threads=None, workers=None)
    with pytest.raises(RuntimeError, match="stop here"):
        bench.run_many(Path("d.json"), tmp_path, args, "old", [], str(tmp_path / "old"))
    assert seen["env"]["PYTHONPATH"].split(os.pathsep) == [str(tmp_path / "old"), "/deps/site", str(bench.ROOT)]
    assert seen["cwd"] == str(tmp_path / "old")


def test_many_class_helpers_split_classes_and_fit_fixed_costs(tmp_path: Path):
    """The many-class benchmark's procedural stand-in splits each category round-robin into renamed classes
    with the same metadata; its fixed cost per class is the intercept of a least-squares line (numpy's polyfit)."""
    import numpy as np

    bench = load_tool("benchmark", "benchmark_tool")
    cats = [{"id": 1, "name": "car", "symmetry": "none"}, {"id": 2, "name": "bottle", "symmetry": "rotational"}]
    anns = [{"id": i, "image_id": i, "category_id": 1 + i % 2} for i in range(10)]
    src = tmp_path / "src" / "annotations.json"
    src.parent.mkdir()
    src.write_text(json.dumps({"categories": cats, "annotations": anns,
                               "images": [{"id": i, "file_name": f"{i}.png"} for i in range(10)]}))
    bench.split_classes(src, tmp_path / "dst", 3)
    out = json.loads((tmp_path / "dst" / "annotations.json").read_text())
    names = {c["id"]: c for c in out["categories"]}
    assert sorted(c["name"] for c in names.values()) == ["bottle_0", "bottle_1", "bottle_2", "car_0", "car_1", "car_2"]
    assert all(c["symmetry"] == ("rotational" if c["name"].startswith("bottle") else "none") for c in names.values())
    per = {}
    for a in out["annotations"]:
        per.setdefault(names[a["category_id"]]["name"], []).append(a["id"])
    assert per["car_0"] == [0, 6] and per["car_1"] == [2, 8] and per["car_2"] == [4] and per["bottle_2"] == [5]
    assert out["images"][0]["file_name"] == "../src/0.png"

    objects = [32, 40, 48, 56, 64, 80]
    rng = np.random.default_rng(0)
    sfm = [1.5 + 0.02 * n + e for n, e in zip(objects, rng.normal(0, 0.05, len(objects)))]
    summary = {"classes": {f"c{i}": {"status": "ok", "objects": n, "reconstructed": n,
                                     "seconds": {"sfm": t, "carve": 0.05 * n, "mesh": 9.0}}
                           for i, (n, t) in enumerate(zip(objects, sfm))}}
    fits = bench.class_costs(summary)["fits"]
    slope, intercept = np.polyfit(objects, sfm, 1)
    assert fits["sfm"]["fixed_per_class"] == pytest.approx(intercept, rel=1e-9)
    assert fits["sfm"]["per_object"] == pytest.approx(slope, rel=1e-9)
    assert fits["carve"]["fixed_per_class"] == pytest.approx(0.0, abs=1e-9)
    assert "mesh" not in fits  # the writers' stages overlap the run: not a cost of the main process


TOOLS = sorted(p.name for p in (ROOT / "tools").glob("*.py"))


def test_tools_are_few_and_import_the_installed_package():
    """At most 10 maintained scripts; none edits sys.path or imports another tool."""
    assert len(list((ROOT / "tools").iterdir())) <= 10
    names = {Path(t).stem for t in TOOLS}
    for tool in TOOLS:
        text = (ROOT / "tools" / tool).read_text()
        assert "sys.path" not in text, tool
        for name in names:
            assert f"import {name}\n" not in text and f"from {name} import" not in text, (tool, name)


def test_tools_read_cpu_time_and_memory_through_runtime():
    """CPU seconds and peak memory come from ``carvi_torch.runtime`` (``cpu_seconds``, ``peak_rss_mb``), one clock
    for every tool and the scripts they start: no tool reads ``resource.getrusage`` itself, and those that time
    CPU or memory name runtime's functions."""
    for tool in TOOLS:
        text = (ROOT / "tools" / tool).read_text()
        assert "getrusage" not in text and "import resource" not in text, tool
    for tool in ("bench_export.py", "studies.py", "benchmark.py", "benchmark_synthetic.py", "bench_viewpoints.py"):
        assert "cpu_seconds(children=True)" in (ROOT / "tools" / tool).read_text(), tool
    assert (ROOT / "tools" / "bench_export.py").read_text().count("peak_rss_mb()") == 2  # the reader, the report


#: ``python SCRIPT --help`` as a fresh process runs it (``__main__``, that argv).
_HELP = "import runpy, sys; sys.argv = [{s!r}, '--help']; runpy.run_path({s!r}, run_name='__main__')"


@pytest.fixture(scope="module")
def helps() -> dict[str, subprocess.CompletedProcess]:
    """Every tool's ``--help``, each in a fresh process of its own (forked from the session's server, so
    torch's import is paid once; nothing one tool imports can make another's work): tool -> its status,
    stdout and stderr."""
    scripts = [str(ROOT / "tools" / t) for t in TOOLS]
    done = run_each_in_a_fresh_process([_HELP.format(s=s) for s in scripts], cwd=ROOT)
    return {t: subprocess.CompletedProcess([sys.executable, s, "--help"], *r) for t, s, r in zip(TOOLS, scripts, done)}


@pytest.mark.parametrize("tool", TOOLS)
def test_every_tool_answers_help(tool: str, helps):
    """Each tool starts (its imports resolve against the current package) and documents its command line."""
    res = helps[tool]
    assert res.returncode == 0, res.stderr[-2000:]
    assert "usage:" in res.stdout and f"tools/{tool}" in (ROOT / "tools" / tool).read_text().split('"""')[1]


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


GPU_SESSION = ROOT / "tools" / "gpu_session.sh"


def _plan(env_steps: str | None = None) -> tuple[int, str, list[tuple[str, str]], int]:
    """``gpu_session.sh --plan`` (STEPS=env_steps when given): status, output, (step, limit) rows, the sum."""
    import re

    env = {k: v for k, v in os.environ.items() if k != "STEPS"}
    if env_steps is not None:
        env["STEPS"] = env_steps
    res = subprocess.run(["bash", str(GPU_SESSION), "--plan"], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=30)
    rows = re.findall(r"^  (\S+) +(\d+|\?) s  ", res.stdout, flags=re.M)
    total = re.search(r"^  sum +(\d+) s", res.stdout, flags=re.M)
    return res.returncode, res.stdout, [r for r in rows if r[0] != "sum"], int(total.group(1)) if total else -1


def test_gpu_session_plan_fits_the_budget_and_names_real_steps(tmp_path: Path):
    """The plan of ``all`` and ``lease`` (``--plan`` runs nothing): its limits add up to at most 470 s of the
    machine's 8 minutes, and the script runs every step it names (none is refused as unknown)."""
    rc, text, rows, total = _plan()
    assert rc == 0, text
    names = [n for n, _ in rows]
    assert {"tests", "e2e9087", "many4", "cad5"} <= set(names), text
    assert total == sum(int(lim) for _, lim in rows) <= 470, text
    assert "UNKNOWN" not in text and "not valid" not in text
    assert f"{total} s in all" in (ROOT / "docs" / "benchmarks.md").read_text()  # the docs give the plan's sum
    for name in names:  # a Python that fails at once: each step starts, fails its checks, and is not "unknown"
        res = subprocess.run(["bash", str(GPU_SESSION), name, str(tmp_path / name)], cwd=tmp_path,
                             env=dict(os.environ, PYTHON="false", DEVICES=""), capture_output=True, text=True,
                             timeout=60)
        assert "unknown step" not in res.stderr, (name, res.stderr)
    # the check can fail: an unknown step, a step without seconds, a plan over the budget
    assert _plan("tests:130 nosuch:5")[0] == 1 and "UNKNOWN STEP" in _plan("tests:130 nosuch:5")[1]
    assert _plan("bench9087")[0] == 1
    rc, text, _, total = _plan("tests:300 cad5:200")
    assert rc == 1 and total == 500 and "OVER its budget" in text


def test_gpu_session_script_is_valid_bash():
    """``bash -n`` parses the script; shellcheck (where installed) finds nothing."""
    import shutil

    res = subprocess.run(["bash", "-n", str(GPU_SESSION)], capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    if shutil.which("shellcheck"):
        res = subprocess.run(["shellcheck", str(GPU_SESSION)], capture_output=True, text=True, timeout=60)
        assert res.returncode == 0, res.stdout


def test_gpu_session_answers_help():
    res = subprocess.run(["bash", str(GPU_SESSION), "--help"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    usage = "bash tools/gpu_session.sh [all|lease|tests|e2e9087|many4|cad5|mesher2000|loading2000|"
    assert res.returncode == 0 and usage in res.stdout
    assert "\nplan: each step under `timeout`" in res.stdout and "  sum " in res.stdout  # the plan, from the code


#: Stands in for ``python`` on a CUDA machine: the package and device checks pass, ``tools/benchmark.py`` writes its
#: record at once (the ``mesher=skimage`` run after FAKE_OLD_SLEEP seconds); anything else runs on this interpreter.
_FAKE_CUDA_PYTHON = """#!{python}
import json, os, sys, time
argv = sys.argv[1:]
if argv[:1] == ["-c"] and (argv[2:3] == ["check"] or "cuda.is_available" in argv[1]):
    sys.exit(0)
if argv and argv[0].endswith("benchmark.py") and "--many-classes" in argv:
    on_cuda, procs = "viewpoints.device=run" in argv, any(a.startswith("viewpoint_processes=") for a in argv)
    if on_cuda:
        time.sleep(float(os.environ.get("FAKE_OLD_SLEEP", "0")))
    wall = 8.0 if on_cuda else 3.0 if procs else 4.0
    rec = {{"many_classes": {{"best": {{"new": {{"wall_seconds_with_startup": wall}}}}}}}}
    json.dump(rec, open(argv[argv.index("--out") + 1], "w"))
    sys.exit(0)
if argv and argv[0].endswith("benchmark.py") and "--load-only" in argv:
    rec = {{"loading": {{"best_seconds": {{"one thread": 1.5}},
                        "resampling": {{"batched_over_reference": 0.4, "same_canvases": True}}}}}}
    json.dump(rec, open(argv[argv.index("--out") + 1], "w"))
    sys.exit(0)
if argv and argv[0].endswith("benchmark.py"):
    old = "mesher=skimage" in argv
    if old:
        time.sleep(float(os.environ.get("FAKE_OLD_SLEEP", "0")))
    rec = {{"end_to_end": {{"wall_seconds_with_startup": 5.0 if old else 2.5}},
           "meshing": None if old else {{"torch_over_skimage": 0.05}}}}
    json.dump(rec, open(argv[argv.index("--out") + 1], "w"))
    sys.exit(0)
os.execv(sys.executable, [sys.executable, *argv])
"""


@pytest.mark.parametrize("old_sleep", [0, 60])
def test_gpu_session_mesher_step_writes_a_ratio_or_a_bound(tmp_path: Path, old_sleep: int):
    """``mesher2000`` in a step of 8 s (``STEP_SECONDS``): both runs finish -> new / old from their records
    (2.5 / 5.0); the old run stopped at its share -> a bound, the new run's recorded seconds over the old run's
    limit."""
    import re

    fake = tmp_path / "python"
    fake.write_text(_FAKE_CUDA_PYTHON.format(python=sys.executable))
    fake.chmod(0o755)
    out, step = tmp_path / "gpu", 8  # the stopped run waits out its limit: about 3 s (8 less the 3 s kept, a second)
    env = dict(os.environ, PYTHON=str(fake), CARVI_GPU_READY="1", FAKE_OLD_SLEEP=str(old_sleep),
               STEP_SECONDS=str(step))
    proc = subprocess.run(["bash", str(GPU_SESSION), "mesher2000", str(out)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=60)
    ratios = (out / "ratios.txt").read_text()
    if old_sleep == 0:
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert ("mesher2000_auto 2.5 s, mesher2000_skimage 5.0 s: mesher2000_auto / mesher2000_skimage 0.500"
                in ratios), ratios
        assert "2000 objects, marching cubes of 100 grids: batched torch op / scikit-image 0.050" in ratios
        return
    assert proc.returncode == 1  # a run stopped at its limit fails the step
    rc, _, limit = (out / "mesher2000_skimage.run").read_text().split()
    wall = float((out / "mesher2000_auto.run").read_text().split()[1])
    assert rc == "124" and 1 <= int(limit) <= step - 3  # the step's end less the 3 s kept for the ratios
    m = re.search(r"mesher2000_skimage stopped at its (\d+) s limit: mesher2000_auto / mesher2000_skimage < ([0-9.]+)",
                  ratios)
    assert m and m.group(1) == limit and float(m.group(2)) == pytest.approx(wall / int(limit), abs=1e-3), ratios


def test_gpu_session_loading_step_writes_the_resampling_ratio(tmp_path: Path):
    """``loading2000``: the load's seconds and the batched resampling over the per-object reference, from the
    record, with whether their canvases agree."""
    fake = tmp_path / "python"
    fake.write_text(_FAKE_CUDA_PYTHON.format(python=sys.executable))
    fake.chmod(0o755)
    out = tmp_path / "gpu"
    env = dict(os.environ, PYTHON=str(fake), CARVI_GPU_READY="1", STEP_SECONDS="8")
    proc = subprocess.run(["bash", str(GPU_SESSION), "loading2000", str(out)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert ("loading 2000 objects: 1.50 s; resampling: batched op / per-object reference 0.400 (the same canvases: "
            "True)") in (out / "ratios.txt").read_text()


@pytest.mark.parametrize("step, variants, old_sleep", [("many4", "procs vprun", 0), ("many4", "vprun", 60),
                                                      ("manyclasses", None, 0), ("many4", None, 0)])
def test_gpu_session_many_class_steps_write_ratios_or_bounds(tmp_path: Path, step: str, variants, old_sleep: int):
    """``many4`` (its variants as asked; by default ``procs`` alone) and ``manyclasses`` (both variants) in a step
    of 10 s: the default (``auto``) against ``viewpoints.device=run`` as new / old (4.0 / 8.0), or a bound when
    the CUDA run is stopped at its share; ``viewpoint_processes`` (the classes' count, at most 12) against the
    default (3.0 / 4.0)."""
    import re

    fake = tmp_path / "python"
    fake.write_text(_FAKE_CUDA_PYTHON.format(python=sys.executable))
    fake.chmod(0o755)
    out = tmp_path / "gpu"
    env = dict(os.environ, PYTHON=str(fake), CARVI_GPU_READY="1", FAKE_OLD_SLEEP=str(old_sleep), STEP_SECONDS="10",
               MANY_RUN_S="3", MANY_ALL_S="3")
    if variants is not None:
        env["MANY4_VARIANTS"] = variants
    proc = subprocess.run(["bash", str(GPU_SESSION), step, str(out)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=60)
    ratios = (out / "ratios.txt").read_text()
    assert proc.returncode == (1 if old_sleep else 0), proc.stdout + proc.stderr
    vprun = step == "manyclasses" or "vprun" in (variants or "")
    procs = step == "manyclasses" or "procs" in (variants or "procs")
    if vprun and old_sleep == 0:
        assert f"{step}_default 4.0 s, {step}_vprun 8.0 s: {step}_default / {step}_vprun 0.500" in ratios, ratios
    elif vprun:
        m = re.search(r"many4_vprun stopped at its (\d+) s limit: many4_default / many4_vprun < ([0-9.]+)", ratios)
        assert m and m.group(1) == "3" and 0 <= float(m.group(2)) < 1, ratios
    else:
        assert "vprun" not in ratios, ratios
    if procs:
        assert f"{step}_procs 3.0 s, {step}_default 4.0 s: {step}_procs / {step}_default 0.750" in ratios, ratios
        count = 12 if step == "manyclasses" else 4
        assert f"viewpoint_processes={count}" in (out / f"{step}_procs.txt").read_text() + (
            out / f"{step}_procs.run").read_text() + proc.stdout
    else:
        assert "procs" not in ratios, ratios


def test_gpu_session_refuses_an_unknown_many_class_variant(tmp_path: Path):
    """A variant the script does not know (here the name of one it had before) stops the step with a reason,
    instead of timing another variant under that name."""
    env = dict(os.environ, PYTHON="false", CARVI_GPU_READY="1", STEP_SECONDS="5", MANY_VARIANTS="vpcpu")
    proc = subprocess.run(["bash", str(GPU_SESSION), "manyclasses", str(tmp_path / "gpu")], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "unknown variant 'vpcpu'" in proc.stderr, proc.stdout + proc.stderr
    assert not (tmp_path / "gpu" / "manyclasses_vpcpu.run").exists()


def test_gpu_session_lease_runs_each_step_under_its_limit_and_packs_after_each(tmp_path: Path):
    """``lease``: every step runs with its own time limit, its start, end and status go to ``steps.txt``, and
    the results are packed after each step (here a step that fails at once and one stopped at its limit)."""
    import tarfile

    fake = tmp_path / "fakepython"  # the package and device checks pass, then it sleeps past the step's limit
    fake.write_text('#!/bin/sh\n[ "$3" = check ] && exit 0\ncase "$2" in *cuda*|*torch.__version__*) exit 0 ;; esac\n'
                    'sleep 30\n')
    fake.chmod(0o755)
    out, pack = tmp_path / "gpu", tmp_path / "results.tgz"
    env = dict(os.environ, PYTHON=str(fake), STEPS="nosuch:5 tests:2", PACK=str(pack))
    proc = subprocess.run(["bash", str(ROOT / "tools" / "gpu_session.sh"), "lease", str(out)], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    steps = (out / "steps.txt").read_text()
    assert "end nosuch, status 2" in steps and "end tests, status 124" in steps, steps
    assert "unknown step 'nosuch'" in (out / "nosuch.log").read_text()
    with tarfile.open(pack) as tar:
        assert {"./steps.txt", "./nosuch.log", "./tests.log", "./plan.txt"} <= set(tar.getnames())


def _cad_runs(out: Path, step: str, turn_deg: float) -> set:
    """Fake 8-view camera runs where ``gpu_session.sh STEP`` looks for them (``viewpoints_cad.recon_dir`` of its
    overrides; cad5 names its classes and splits its CUDA side into processes of a few classes each): on both
    devices class ``a`` (cad5: in the first CUDA process, ``c`` in the second), the CUDA camera of every object
    turned by ``turn_deg`` about z; class ``b`` on the CPU alone (a CUDA run stopped before it). Returns the
    classes both sides have."""
    import math
    import re

    recon_dir = load_tool("viewpoints_cad").recon_dir
    text = GPU_SESSION.read_text()
    cpu_ovr, cuda_runs = [], [([], ("a",))]
    if step == "cad5":
        cpu_classes = re.search(r"^CAD5_CLASSES=[$][{]CAD_CLASSES:-([^}]+)[}]", text, flags=re.M).group(1)
        cpu_ovr = [f"classes=[{cpu_classes}]"]
        groups = re.search(r"^CAD5_CUDA_GROUPS=[$][{]CAD_CLASSES:-([^}]+)[}]", text, flags=re.M).group(1).split()
        assert len(groups) == 2
        cuda_runs = [([f"classes=[{groups[0]}]"], ("a",)), ([f"classes=[{groups[1]}]"], ("c",))]

    def rot(deg):
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        return [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]

    runs = [(["device=cpu", *cpu_ovr], ("a", "b", "c") if step == "cad5" else ("a", "b"), 0.0)]
    runs += [(["device=cuda", "viewpoints.device=run", *ovr], classes, turn_deg) for ovr, classes in cuda_runs]
    for ovr, classes, deg in runs:
        run = recon_dir(out / step, ovr, views=8, seed=2)
        for cls in classes:
            (run / cls).mkdir(parents=True)
            cams = {str(i): {"refined": {"R": rot(deg)}, "camera_choice": "refined"} for i in range(3)}
            (run / cls / "cameras.json").write_text(json.dumps({"cameras": cams}))
        summary = {"torch_threads": 2, "classes": {c: {"objects": 3, "seconds": {"sfm": 1.0, "refine": 0.5}}
                                                   for c in classes}}
        (run / "summary.json").write_text(json.dumps(summary))
    return {"a", "c"} if step == "cad5" else {"a"}


@pytest.mark.parametrize("step, turn_deg, status", [("cad8", 0.3, 0), ("cad5", 0.8, 1)])
def test_gpu_session_cad_steps_compare_the_runs_they_find(tmp_path: Path, step: str, turn_deg: float, status: int):
    """``DEVICES= gpu_session.sh cad8|cad5`` compares the CPU and CUDA cameras already there, in the folders that
    tools/viewpoints_cad.py gives those runs (cad5: its CUDA processes' folders together): the angle between them
    per class against the 0.5 degree tolerance (exit status), a class the CUDA run missed named as such, the
    comparison's lines in ratios.txt."""
    both = _cad_runs(tmp_path, step, turn_deg)
    # CARVI_GPU_READY: the packages are known to be there, so the script skips its check (an interpreter that
    # imports torch, seconds; test_gpu_session_keeps_the_callers_python_path covers it) and leaves the path to us
    path = os.pathsep.join([str(ROOT), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)])
    env = dict(os.environ, DEVICES="", PYTHON=sys.executable, CARVI_GPU_READY="1", PYTHONPATH=path)
    env.pop("CAD_CLASSES", None)
    proc = subprocess.run(["bash", str(GPU_SESSION), step, str(tmp_path)], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == status, proc.stdout + proc.stderr
    assert "b            not reached by the cuda run" in proc.stdout
    rec = json.loads((tmp_path / f"{step}_agreement.json").read_text())
    assert set(rec["classes"]) == both
    for cls in both:
        assert rec["classes"][cls]["median_deg"] == pytest.approx(turn_deg, abs=1e-3)
        assert rec["classes"][cls]["camera_choice_differs"] == 0
    n = len(both)
    assert rec["viewpoint_seconds"] == {"cpu": 1.5 * n, "cuda": 1.5 * n}
    ratios = (tmp_path / "ratios.txt").read_text()
    assert f"{step}: {n} classes compared" in ratios and f"{step}: largest class median {turn_deg:.3f} deg" in ratios
    assert (f"{step}: SfM + refinement of the classes compared, cuda {1.5 * n:.1f} s / cpu {1.5 * n:.1f} s: cuda / cpu "
            "1.000") in ratios


STRESS = ROOT / "tools" / "stress_inputs.py"


def test_stress_inputs_runs_a_few_cases(tmp_path: Path):
    """A few of the hostile-input cases through the real command line (a valid file, a truncated JSON,
    a bad device, another command's --out that is a file): each comes out as promised, so the tool exits 0
    and its table marks every row good."""
    cases = ["control_valid", "json_truncated", "cli_device_tpu", "cmd_datasets_procedural_out_file"]
    record = tmp_path / "stress.json"
    res = subprocess.run([sys.executable, str(STRESS), "--work", str(tmp_path / "work"), "--cases", ",".join(cases),
                          "--out-json", str(record), "--jobs", str(len(cases))],  # all at once: two exit early
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    lines = res.stdout.splitlines()
    assert lines[:2] == ["| case | what is wrong | outcome | good? |", "|---|---|---|---|"]
    rows = {ln.split("|")[1].strip(" `"): ln for ln in lines[2:] if ln.startswith("| `")}
    assert sorted(rows) == sorted(cases) and all(r.endswith("| yes |") for r in rows.values()), rows
    assert "exit 2: error: --out file is a file" in rows["cmd_datasets_procedural_out_file"]
    assert "exit 2: error: device" in rows["cli_device_tpu"] and "exit 0; 12 objects" in rows["control_valid"]
    rec = json.loads(record.read_text())["cases"]
    assert [(c["case"], c["exit"], c["good"]) for c in rec] == [
        ("control_valid", [0], True), ("json_truncated", [2], True), ("cli_device_tpu", [2], True),
        ("cmd_datasets_procedural_out_file", [2], True)]


def test_stress_inputs_checks_catch_bad_outcomes(tmp_path: Path):
    """The tool's checks flag what they must: a wrong exit status, a traceback, a missing phrase, a
    file outside --out, a good object not made, a process of the run left running."""
    st = load_tool("stress_inputs")
    ctx = st.Ctx(st.Case("x", "x", rc=2, error=("device",)), tmp_path / "case", tmp_path, {"annotations": []}, 10)
    ctx.out.parent.mkdir(parents=True)
    before = st.snapshot(ctx.dir)
    (ctx.dir / "stray.txt").write_text("x")
    proc = st.Proc([], 1, "", "Traceback (most recent call last):\nValueError: x\n", 0.1)
    problems = " / ".join(st.check_exit(ctx, proc) + st.check_streams(ctx, proc) + st.check_writes(ctx, before))
    for what in ("exit status 1, expected 2", "Traceback on stderr", "does not say 'device'", "outside --out"):
        assert what in problems, problems
    ctx.good = [1]
    assert st.check_good(ctx) and not st.check_processes(ctx, wait=0.1)
    left = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], env=ctx.env())
    try:
        time.sleep(0.5)
        assert "still running" in " ".join(st.check_processes(ctx, wait=0.5))
    finally:
        left.kill()
        left.wait()


def test_stress_inputs_never_imports_a_module_of_the_case_folder(tmp_path: Path):
    """A case's command runs in its folder, among the crafted files: a ``yaml.py`` there is not imported (``python
    -m`` puts the working folder first on ``sys.path``; the tool passes ``-P``)."""
    st = load_tool("stress_inputs")
    ctx = st.Ctx(st.Case("planted", "a yaml.py in the case folder", cli=()), tmp_path / "case", tmp_path, {}, 120)
    ctx.dir.mkdir()
    (ctx.dir / "yaml.py").write_text("import sys\nprint('planted module imported', file=sys.stderr)\nsys.exit(3)\n")
    proc = st.invoke(ctx, extra=["--help"])
    assert proc.rc == 0 and "planted" not in proc.stderr + proc.stdout, proc.stderr[-2000:]


def test_synthetic_benchmark_seeds_table_and_keyed_record(tmp_path: Path):
    """Several seeds: per class and method every seed's mean, missing objects and the mean over the seeds
    (checked by hand on two classes); the record goes under ``--key`` with the file's other keys kept, and a
    top-level write keeps the keyed records; ``--methods`` is case-insensitive and needs Full."""
    bs = load_tool("benchmark_synthetic", "benchmark_synthetic_tool")

    def res(a, b, miss):
        classes = {"bottle": {"Full": {"mean": a, "count": 8 - miss, "missing": miss}},
                   "train": {"Full": {"mean": b, "count": 8, "missing": 0}}}
        return {"methods": ["Full"], "classes": classes, "mean_over_classes": {"Full": (a + b) / 2}}

    per_seed = {0: res(4.0, 6.0, 1), 1: res(5.0, 9.0, 0)}
    table = bs.seeds_table(per_seed)
    assert "| bottle (8) | 4.00 [1 missing] | 5.00 | 4.50 |" in table
    assert "| train (8) | 6.00 | 9.00 | 7.50 |" in table
    assert "| **mean, 2 classes** | **5.00** | **7.00** | **6.00** |" in table
    rec = bs.seeds_record(per_seed, {0: {"a": 0}, 1: {"a": 1}}, "cmd")
    assert rec["table"]["train"]["Full"] == {"0": 6.0, "1": 9.0, "mean": 7.5}
    assert rec["missing"]["bottle"]["Full"] == {"0": 1, "1": 0}
    assert rec["mean_over_classes"]["Full"] == {"0": 5.0, "1": 7.0, "mean": 6.0}
    path = tmp_path / "benchmark_synthetic.json"
    path.write_text(json.dumps({"table": "old", "command": "old"}))
    bs.write_results(path, rec, "shapes8")
    assert json.loads(path.read_text())["table"] == "old"
    bs.write_results(path, {"table": "new", "command": "new"}, None)
    records = json.loads(path.read_text())
    assert records["table"] == "new" and records["shapes8"]["seeds"] == [0, 1]
    assert bs.parse_methods("oracle,full") == ["Full", "oracle"]
    with pytest.raises(ValueError, match="must include Full"):
        bs.parse_methods("oracle")


def _three_sided_models(folder: Path) -> Path:
    """Three CAD-like ``thing`` models, the last naming its left/right pair from the other side."""
    folder.mkdir()
    verts = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    faces = np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3], [0, 2, 3]], np.int32)
    for i, side in enumerate([-0.8, -0.8, 0.8]):  # pair b names the sides alike on all three
        np.savez(folder / f"thing0{i}.npz", vertices=verts, faces=faces,
                 keypoint_names=np.array(["left_a", "right_a", "left_b", "right_b", "top"]),
                 keypoints=np.array([[side, 0, 0.2], [-side, 0, 0.2], [-0.5, 0, 0], [0.5, 0, 0], [0, 0, 1]],
                                    np.float32))
    return folder


def test_cad_renders_made_otherwise_are_refused_or_redone(tmp_path: Path):
    """CAD renders on disk are reused only when made with the run's settings, models and left/right names
    (``render_mismatch``): the viewpoint benchmark stops with the reason, the shape benchmark renders again.
    Renders of other models under the same ``--work`` (their swaps alike) and renders made before the names
    were harmonised (no ``side_swaps`` in their info) are both refused."""
    import argparse
    import shutil
    import warnings

    from carvi_torch.synthetic import load_models

    vc = load_tool("viewpoints_cad")
    bs = load_tool("benchmark_synthetic", "benchmark_synthetic_tool")
    vc._models.cache_clear()
    cad = _three_sided_models(tmp_path / "cad")
    args = argparse.Namespace(work=str(tmp_path / "w"), views=1, cameras="photo", sides="class", cad=str(cad),
                              quiet=True)
    with pytest.warns(UserWarning, match="thing02"):
        renders = vc._renders(args, 0)
    info = json.loads((renders / "annotations.json").read_text())["info"]
    assert info["side_swaps"] == {"thing02": [["left_a", "right_a"]]}
    models = list(vc._models(str(cad), "class"))
    assert bs._render_mismatch(renders, models, 1, 0, 0) is None
    assert bs._render_mismatch(renders, models, 2, 0, 0) == "views: 1 recorded, 2 wanted"
    assert bs._render_mismatch(renders, load_models(cad, sides="as-given"), 1, 0, 0) == \
        "other left/right names: thing02: [['left_a', 'right_a']] recorded, none wanted"
    stamp = (renders / "annotations.json").stat().st_mtime_ns
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the models are read once per (--cad, --sides): no second warning
        assert vc._renders(args, 0) == renders and (renders / "annotations.json").stat().st_mtime_ns == stamp
    args.sides = "as-given"
    as_given = vc._renders(args, 0)
    assert as_given != renders and json.loads((as_given / "annotations.json").read_text())["info"]["side_swaps"] == {}
    more = tmp_path / "cad4"  # one more model, named like the first: the same side_swaps, other renders
    shutil.copytree(cad, more)
    shutil.copy(cad / "thing00.npz", more / "thing03.npz")
    args.cad, args.sides = str(more), "class"
    with pytest.warns(UserWarning, match="thing02"), \
            pytest.raises(SystemExit, match=r"models: 3 recorded, 4 wanted; not recorded: thing03"):
        vc._renders(args, 0)
    args.cad = str(cad)
    data = json.loads((renders / "annotations.json").read_text())
    del data["info"]["side_swaps"]
    (renders / "annotations.json").write_text(json.dumps(data))
    vc._models.cache_clear()
    with pytest.warns(UserWarning, match="thing02"), pytest.raises(SystemExit, match="side_swaps not recorded"):
        vc._renders(args, 0)
    assert bs._render_mismatch(renders, models, 1, 0, 0) == "side_swaps not recorded (rendered by an older version)"
    (renders / "gt.json").unlink()
    assert bs._render_mismatch(renders, models, 1, 0, 0) == "no gt.json"
    assert vc._renders(args, 0) == renders  # a folder without gt.json is incomplete: rendered again
    assert (renders / "gt.json").is_file() and bs._render_mismatch(renders, models, 1, 0, 0) is None


def test_many_class_cad_renders_are_reused_only_as_the_command_would_make_them(tmp_path: Path, monkeypatch):
    """``benchmark.ensure_many_classes`` renders with ``carvi datasets synthetic`` (run here in-process), then
    reuses what that command made (its defaults are ``render_dataset``'s), and renders again what another
    seed or older renders left; without the CAD models it takes what is there."""
    import warnings

    from carvi_torch import cli

    bench = load_tool("benchmark", "benchmark_tool")
    cad = _three_sided_models(tmp_path / "cad")
    calls = []

    def run(cmd, cwd, check):
        assert cmd[1:3] == ["-m", "carvi_torch.cli"] and check
        calls.append(cmd)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert cli.main(cmd[3:]) == 0

    monkeypatch.setattr(bench.subprocess, "run", run)
    ann = bench.ensure_many_classes(tmp_path / "data", 1, cad)
    assert len(calls) == 1 and ann == tmp_path / "data" / "cad_v8_s1" / "annotations.json"
    info = json.loads(ann.read_text())["info"]
    assert info["views"] == 8 and info["seed"] == 1 and info["side_swaps"] == {"thing02": [["left_a", "right_a"]]}
    assert bench.ensure_many_classes(tmp_path / "data", 1, cad) == ann and len(calls) == 1  # reused
    data = json.loads(ann.read_text())
    data["info"]["seed"] = 0  # what seed 0's folder would hold
    ann.write_text(json.dumps(data))
    assert bench.ensure_many_classes(tmp_path / "data", 1, cad) == ann and len(calls) == 2
    assert json.loads(ann.read_text())["info"]["seed"] == 1
    del data["info"]["side_swaps"]
    ann.write_text(json.dumps(data))
    assert bench.ensure_many_classes(tmp_path / "data", 1, tmp_path / "absent") == ann and len(calls) == 2


def test_synthetic_benchmark_redoes_reconstructions_of_renders_made_again(tmp_path: Path, monkeypatch):
    """``run_seed``: renders made now are reused with their finished runs; renders made with other left/right names
    are rendered again and every run is redone over its folder (``overwrite=true``), finished or not."""
    import argparse

    bs = load_tool("benchmark_synthetic", "benchmark_synthetic_tool")
    from carvi_torch.synthetic import load_models

    cad = _three_sided_models(tmp_path / "cad")
    with pytest.warns(UserWarning, match="thing02"):
        models = load_models(cad)
    args = argparse.Namespace(models=str(cad), pool=1, test_views=0, sides="class", jobs=1, fresh=False, set=[],
                              step_percent=1.0, no_baselines=True)
    started = []

    class Stop(Exception):
        pass

    def run_parallel(commands, jobs, threads):
        started.append([(name, argv) for name, argv, _ in commands])
        raise Stop

    def run() -> list:
        started.clear()
        with pytest.warns(UserWarning, match="thing02"), pytest.raises(Stop):
            bs.run_seed(args, 0, tmp_path / "out", ["Full"], None, "cmd")
        data = tmp_path / "out" / "data_pool1_test0_seed0"
        assert bs._render_mismatch(data, models, 1, 0, 0) is None
        return started[0]

    monkeypatch.setattr(bs, "run_parallel", run_parallel)
    monkeypatch.setattr(bs, "_finished", lambda run: True)
    (first,) = run()
    assert first[0] == "Full" and "overwrite=true" in first[1]
    _fake_reconstruct(first[1])
    assert all(name != "Full" for name, _ in run())  # reused: the first commands started are the evaluation's
    ann = tmp_path / "out" / "data_pool1_test0_seed0" / "annotations.json"
    data = json.loads(ann.read_text())
    del data["info"]["side_swaps"]  # made before the names were harmonised
    ann.write_text(json.dumps(data))
    (again,) = run()
    assert again[0] == "Full" and "overwrite=true" in again[1]


def test_synthetic_benchmark_help_names_the_small_class_runs_as_recorded():
    """The small-class benchmark's ``--pool`` and ``--test-views`` in the tool's help are those of the
    ``shapes_cad8*`` records' commands (docs/results.md)."""
    import re

    bs = load_tool("benchmark_synthetic", "benchmark_synthetic_tool")
    said = re.findall(r"--pool \d+ --test-views \d+", " ".join(bs._parser().format_help().split()))
    records = json.loads((ROOT / "docs" / "data" / "benchmark_synthetic.json").read_text())
    run = {re.search(r"--pool \d+ --test-views \d+", v["command"]).group(0)
           for k, v in records.items() if k.startswith("shapes_cad8")}
    assert len(run) == 1 and said == list(run), (said, run)


@pytest.mark.parametrize("study", ["misses", "own-shapes"])
def test_rendered_studies_help_names_the_record_they_write(study: str, capsys):
    """The default record a study of rendered sets writes (``_record(<name>)`` in tools/studies.py) is the
    one its ``--help`` names."""
    st = load_tool("studies", "studies_tool")
    name = f"studies_{study.replace('-', '_')}.json"
    assert f'_record("{study.replace("-", "_")}")' in (ROOT / "tools" / "studies.py").read_text()
    with pytest.raises(SystemExit):
        st.main([study, "--help"])
    assert name in " ".join(capsys.readouterr().out.split())


def test_synthetic_benchmark_without_models_is_one_error_line(tmp_path: Path, capsys):
    """No ``--models`` folder, or one without models: one ``error:`` line naming it, exit 2, nothing written."""
    bs = load_tool("benchmark_synthetic", "benchmark_synthetic_tool")
    (tmp_path / "empty").mkdir()
    for models, why in [(tmp_path / "none", "not found"), (tmp_path / "empty", "no models")]:
        argv = ["--models", str(models), "--out", str(tmp_path / "out"), "--results", str(tmp_path / "res")]
        assert bs.main(argv) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: --models {models}") and why in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]


def _fake_reconstruct(argv: list) -> Path:
    """What ``reconstruct`` leaves in ``--out`` for the command ``argv`` (its resolved ``config.yaml`` and a
    finished ``summary.json``), without the work."""
    from carvi_torch.config import load_config

    out = Path(argv[argv.index("--out") + 1])
    settings = argv[argv.index("--out") + 2:]
    cfg = load_config(None, settings).override({"data": argv[argv.index("--data") + 1], "out": str(out)})
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(cfg.to_yaml())
    (out / "summary.json").write_text(json.dumps({"total_seconds": 1.0, "classes": {}}))
    return out


def test_synthetic_benchmark_reuses_a_run_only_of_its_data_and_settings(tmp_path: Path, monkeypatch):
    """``run_seed`` reuses a finished run only when its ``config.yaml`` names this seed's renders and the method's
    and ``--set`` settings: switching ``--sides`` (other renders, each folder current) or ``--set`` makes the run
    again over its folder, and the record's settings name ``sides``."""
    import argparse
    import warnings

    bs = load_tool("benchmark_synthetic", "benchmark_synthetic_tool")
    cad = _three_sided_models(tmp_path / "cad")
    args = argparse.Namespace(models=str(cad), pool=1, test_views=0, sides="class", jobs=1, fresh=False, set=[],
                              step_percent=1.0, no_baselines=True)
    started = []

    def run_parallel(commands, jobs, threads):
        for name, argv, _ in commands:
            started.append((name, argv))
            if name == "Full":
                _fake_reconstruct(argv)
            else:  # the evaluation of one class
                out = Path(argv[argv.index("--out") + 1])
                out.mkdir(parents=True, exist_ok=True)
                row = {"Full": {"mean": 1.0, "count": 3, "missing": 0}}
                (out / "results.json").write_text(json.dumps({
                    "methods": ["Full"], "objects": {}, "classes": {"thing": row}, "viewpoints": {},
                    "mean_over_classes": {"Full": 1.0}, "seconds": 0.0}))
        return {}

    def full_runs() -> list:
        started.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # thing02's renamed pair
            _, record = bs.run_seed(args, 0, tmp_path / "out", ["Full"], None, "cmd")
        assert record["settings"]["sides"] == args.sides
        return [argv for name, argv in started if name == "Full"]

    monkeypatch.setattr(bs, "run_parallel", run_parallel)
    (first,) = full_runs()
    assert first[first.index("--data") + 1].endswith("data_pool1_test0_seed0/annotations.json")
    assert full_runs() == []  # reused
    args.sides = "as-given"
    (given,) = full_runs()  # new renders: made again
    assert given[given.index("--data") + 1].endswith("_sides-as-given/annotations.json")
    args.sides = "class"
    (again,) = full_runs()  # the class-named renders are current, the run in run_full is not theirs
    assert again == first and "overwrite=true" in again
    assert full_runs() == []
    args.set = ["carve.imprint=false"]
    (imprint,) = full_runs()
    assert "overwrite=true" in imprint and imprint[-1] == "carve.imprint=false"
    assert full_runs() == []
    (tmp_path / "out" / "run_full" / "summary.json").write_text("{}")  # cut short: resumed, not overwritten
    (resumed,) = full_runs()
    assert "overwrite=true" not in resumed


def test_own_shapes_recover_a_stretched_object_exactly():
    """``studies._own_shapes`` on an analytic case: a mean shape that is the object stretched along the CAD axes (and
    turned by the class's rotation into the SfM frame) gives back the object's keypoints, both ways, at the mean
    shape's size and centre; the stretch factors are the inverse stretch at unit RMS."""
    import torch

    st = load_tool("studies", "studies_tool")
    gen = torch.Generator().manual_seed(0)
    X = torch.randn(8, 3, generator=gen, dtype=torch.float64)
    X = X - X.mean(0)
    q = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))[0]
    G = q * torch.sign(torch.det(q))  # a rotation
    S = (X * torch.tensor([2.0, 0.5, 1.0], dtype=X.dtype) + torch.tensor([1.0, 2.0, 3.0], dtype=X.dtype)) @ G.T
    own, stretched, axes = st._own_shapes(S, G, X)
    Sc = S @ G
    size, centre = (Sc - Sc.mean(0)).norm(), Sc.mean(0)
    want = (X / X.norm() * size + centre) @ G.T
    torch.testing.assert_close(own, want)
    torch.testing.assert_close(stretched, want)
    inv = torch.tensor([0.5, 2.0, 1.0], dtype=X.dtype)
    torch.testing.assert_close(axes, inv / inv.norm() * 3 ** 0.5)
    X[0] = float("nan")  # a keypoint the object lacks keeps the mean shape's point in its own shape
    own, _, _ = st._own_shapes(S, G, X)
    torch.testing.assert_close(own[0], S[0])
    assert st._own_shapes(S, G, torch.full_like(X, float("nan"))) is None


def test_own_shapes_study_refines_the_pipelines_cameras_under_each_objects_shape(tmp_path: Path):
    """``studies.py own-shapes`` through its command line on a small class: its final errors are ``evaluate``'s
    (per model), and refined under each object's own keypoints the cameras come within a degree of the truth."""
    import numpy as np

    from carvi_torch.evaluate import evaluate
    from carvi_torch.reconstruct import main as reconstruct_main
    from carvi_torch.synthetic import procedural

    st = load_tool("studies", "studies_tool")
    procedural.write_default_collection(tmp_path / "set", instances_per_class=6, views_per_instance=2,
                                        categories=["car"], seed=0, progress=False)
    data, recon = tmp_path / "set" / "annotations.json", tmp_path / "recon"
    assert reconstruct_main(["--data", str(data), "--out", str(recon), "--quiet", "stage=cameras",
                             "viewpoints.sfm_groups=1"]) == 0
    rep = evaluate(data, {"estimated": recon}, shapes=False, progress=False)["viewpoints"]["car"]["estimated"]
    out = tmp_path / "records.json"
    assert st.main(["own-shapes", "--data", str(data), "--out", str(out), "--key", "k"]) == 0
    car = json.loads(out.read_text())["k"]["sets"]["set"]["car"]
    assert car["n"] == 12
    assert car["final"] == pytest.approx(np.median(rep["refined"]["per_instance_geodesic"]), abs=0.02)
    assert car["own_shape"] < 1.0 < car["final"] and len(car["models"]) == 6  # refining under the own shape helps


def test_export_quality_study_ranks_against_scipy(tmp_path: Path):
    """``bench_export --quality``: the pooled and per-class Spearman rho of quality against the shape
    error equal scipy's on the same pairs; objects without a quality are left out; a reconstruction
    folder that is not there (a relative --recon read from elsewhere) is one line, not an empty study."""
    from scipy import stats

    be = load_tool("bench_export")
    recon, ev = tmp_path / "recon", tmp_path / "eval"
    errors = {"a": [1.0, 3.0, 2.0, 5.0, 4.0], "b": [2.5, 0.5, 4.5, 1.5, 3.5]}
    quality = {"a": [0.9, 0.4, 0.6, 0.1, 0.3], "b": [0.2, 0.8, 0.3, 0.7, 0.5]}
    objects, pairs = {}, []
    for c in errors:
        cams = {}
        for i, (e, q) in enumerate(zip(errors[c], quality[c])):
            aid = f"{c}{i}"
            objects[aid] = {"class": c, "Full": {"error_percent": e}}
            cams[aid] = {"quality": q, "quality_signals": {"visible_keypoints": 4 + i}}
            pairs.append((q, e))
        objects[f"{c}x"] = {"class": c, "Full": {"error_percent": 9.0}}  # no quality: left out
        (recon / c).mkdir(parents=True)
        (recon / c / "cameras.json").write_text(json.dumps({"cameras": cams}))
    ev.mkdir()
    res = {"recons": {"Full": str(recon)}, "objects": objects, "step_percent": 3.0}
    (ev / "results.json").write_text(json.dumps(res))
    out = tmp_path / "rec.json"
    assert be.quality_study([ev], None, str(out), "q", ["--quality", str(ev)]) == 0
    rec = json.loads(out.read_text())["q"]
    q, e = zip(*pairs)
    assert rec["objects"] == 10
    assert rec["pooled"]["rho"] == pytest.approx(stats.spearmanr(q, e).statistic, abs=1e-4)
    for c in errors:
        assert rec["per_class"][c]["rho"] == pytest.approx(stats.spearmanr(quality[c], errors[c]).statistic, abs=1e-4)
    res["recons"]["Full"] = "recon"  # relative to a folder this process is not in
    (ev / "results.json").write_text(json.dumps(res))
    with pytest.raises(SystemExit, match="no such reconstruction folder"):
        be.quality_study([ev], None, str(out), "q", [])


_PROFILE = """
import runpy, sys
sys.argv = [sys.argv[1], "--profile-mixture", *sys.argv[2:]]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def test_mixture_profile_times_every_group_sfm(tmp_path: Path, procedural_input):
    """``bench_viewpoints --profile-mixture`` (in a fresh process: it wraps module attributes): with the
    mixture fitted for every class, each class's record counts cold and warm group SfMs with their outer
    steps, and its parts' CPU seconds add up to no more than the fit, the fit to no more than the stage."""
    data = procedural_input(tmp_path)
    out = tmp_path / "profile.json"
    args = [str(ROOT / "tools" / "bench_viewpoints.py"), str(data), "--profile-set", "sfm_groups=2",
            "sfm_group_misfit=0", "sfm_group_hull_gain=-1", "sfm_group_min=2", "sfm_max_outer=30", "classes=[car]",
            "--out", str(out), "--key", "prof"]
    out.write_text(json.dumps({"other": 1}))  # a records file: the record joins its keys
    [(rc, stdout, err)] = run_each_in_a_fresh_process([_PROFILE], argv=args, cwd=ROOT)
    assert rc == 0, err[-2000:]
    records = json.loads(out.read_text())
    assert records["other"] == 1 and records["prof"]["overrides"][0] == "sfm_groups=2"
    rec = records["prof"]
    assert rec["classes"] and "group SfMs" in stdout
    for cls, r in rec["classes"].items():
        s, n = r["seconds"], r["counts"]
        if not n.get("cold:group_sfm"):
            continue  # a class too small to split has no group SfM to time
        assert n["cold:outer_steps"] >= n["cold:group_sfm"], cls
        # the parts do not nest and run on one thread (a class under THREADS_MIN_OBJECTS), so their CPU
        # seconds cannot exceed the fit's
        parts = s["cold:group_sfm"] + s.get("warm:group_sfm", 0) + s.get("keypoint_fit", 0) + s.get("kmeans", 0)
        assert parts <= s["mixture_total"] + 1e-3 and s["mixture_total"] <= s["viewpoints_total"] + 1e-3, cls
    assert any(r["counts"].get("cold:group_sfm") for r in rec["classes"].values())


def test_ranking_study_writes_its_figures_where_asked(tmp_path: Path, monkeypatch):
    """``studies.py ranking --figures DIR``: the per-class summary of two references with known errors (a
    loop's top-ranked / mean / minimum) is plotted into DIR, and nothing is written to docs/figures."""
    st = load_tool("studies", "studies_tool")
    docs_figures = {p.name: p.stat().st_mtime_ns for p in (ROOT / "docs" / "figures").glob("*.png")}
    nan = None
    per_ref = {"1": {"class": "sofa", "errors": [5.0, 3.0, nan], "scores": [0.1, 0.2, 0.0], "misses": [0, 0, 0],
                     "valid": [True, True, False], "best": 0},
               "2": {"class": "sofa", "errors": [4.0, 6.0, 2.0], "scores": [0.3, 0.1, 0.2], "misses": [0, 0, 1],
                     "valid": [True, True, True], "best": 1}}
    out = st._ranking_summary(per_ref)
    # reference 1: top = proposal 0 (lowest score among valid); reference 2: proposal 1 (fewest misses, then score)
    assert out["classes"]["sofa"]["top"] == pytest.approx((5.0 + 6.0) / 2)
    assert out["classes"]["sofa"]["random"] == pytest.approx((4.0 + 4.0) / 2)
    assert out["classes"]["sofa"]["best"] == pytest.approx((3.0 + 2.0) / 2)
    assert out["ranking_agrees_with_pipeline"] == "2/2"
    # the command line: cached errors of a rendered benchmark folder, --figures and --record where asked
    bench = tmp_path / "bench"
    (bench / "data_pool1").mkdir(parents=True)
    (bench / "ranking").mkdir()
    anns = [{"id": i, "category_id": 1, "split": "test", "object_id": i} for i in (1, 2)]
    (bench / "data_pool1" / "annotations.json").write_text(json.dumps(
        {"categories": [{"id": 1, "name": "sofa"}], "annotations": anns}))
    (bench / "data_pool1" / "gt.json").write_text(json.dumps({"annotations": {}}))
    (bench / "ranking" / "errors_step2_v2.json").write_text(json.dumps({"per_reference": per_ref, "seconds": 1.0}))
    monkeypatch.setattr(st, "RECORDS", tmp_path / "records")
    assert st.main(["ranking", "--bench", str(bench), "--views-per-model", "2", "--figures", str(tmp_path / "cad8"),
                    "--record", "cad8"]) == 0
    assert sorted(p.name for p in (tmp_path / "cad8").iterdir()) == ["pool_size.png", "ranking.png"]
    rec = json.loads((tmp_path / "records" / "studies_cad8.json").read_text())
    assert rec["classes"]["sofa"]["top"] == pytest.approx(5.5) and rec["references"] == 2
    # --out/--key: the same record under a key of a records file, whose other keys stay
    records = tmp_path / "benchmark_synthetic.json"
    records.write_text(json.dumps({"table": "kept"}))
    assert st.main(["ranking", "--bench", str(bench), "--views-per-model", "2", "--figures", str(tmp_path / "cad8"),
                    "--out", str(records), "--key", "ranking_cad8"]) == 0
    keyed = json.loads(records.read_text())
    assert sorted(keyed) == ["ranking_cad8", "table"] and keyed["table"] == "kept"
    assert {k: v for k, v in keyed["ranking_cad8"].items() if k != "command"} == \
        {k: v for k, v in rec.items() if k != "command"}
    assert {p.name: p.stat().st_mtime_ns for p in (ROOT / "docs" / "figures").glob("*.png")} == docs_figures


_FAKE_RUN = """
import json, pathlib, sys, time
out, burn, sleep, tag = pathlib.Path(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
t = time.process_time()
while time.process_time() - t < burn:
    pass
time.sleep(sleep)
(out / "a").mkdir(parents=True)
(out / "a" / "cameras.json").write_text(tag)
classes = {"a": {"sfm_groups": {"groups": 3, "candidates": [1]}}, "b": {}}
(out / "summary.json").write_text(json.dumps({"classes": classes}))
"""


def test_cameras_cpu_interleaves_variants_and_counts_child_cpu(tmp_path: Path):
    """``bench_viewpoints --cameras-cpu``'s loop on stand-in children (a CPU burner and a sleeper): the
    variants alternate their order by round, a child's CPU seconds are its own (the sleeper's wall time is
    not CPU), the ratios are those of the recorded seconds, and a run whose cameras differ is flagged."""
    bv = load_tool("bench_viewpoints")
    seen = []

    def command(data, out, overrides):
        burn, sleep = (0.15, 0.0) if overrides == ["burn"] else (0.0, 0.15)
        seen.append(overrides[0])
        tag = f"{overrides[0]}{len(seen) if overrides == ['sleep'] else ''}"  # the sleeper's cameras change
        return [sys.executable, "-c", _FAKE_RUN, str(out), str(burn), str(sleep), tag]

    rec = bv.cameras_cpu("unused.json", ["sleep", "burn"], 2, command=command)
    assert seen == ["sleep", "burn", "burn", "sleep"]
    assert [r["order"] for r in rec["runs"]["sleep"]] == [0, 3] and [r["order"] for r in rec["runs"]["burn"]] == [1, 2]
    for r in rec["runs"]["burn"]:
        assert r["cpu_seconds"] >= 0.14 and r["load_average_before"] >= 0
    for r in rec["runs"]["sleep"]:
        assert r["cpu_seconds"] < 0.12 and r["wall_seconds"] >= 0.15
        assert r["groups"] == {"a": 3, "b": 1} and r["fitted"] == ["a"]
    cpu = {v: [r["cpu_seconds"] for r in rs] for v, rs in rec["runs"].items()}
    assert rec["cpu_over_first"]["burn"]["per_round"] == [round(b / s, 3) for b, s in zip(cpu["burn"], cpu["sleep"])]
    assert rec["cpu_over_first"]["burn"]["least"] == round(min(cpu["burn"]) / min(cpu["sleep"]), 3)
    assert rec["same_cameras_every_round"] == {"sleep": False, "burn": True}
    with pytest.raises(SystemExit, match="failed"):
        bv.cameras_cpu("x", ["v"], 1, command=lambda d, o, v: [sys.executable, "-c", "raise SystemExit(3)"])


def test_misses_study_scores_the_pipelines_cameras_against_the_true_ones_refined(tmp_path: Path):
    """``studies.py misses`` through its command line on a small class (two views of each model): its final cameras
    are the pipeline's (each model's median error is numpy's median of ``evaluate``'s errors of a ``reconstruct
    stage=cameras`` run), the true camera put in the SfM frame is the truth again under the class's fitted rotation,
    refining it never raises its energy, and the record joins the file's other keys."""
    import numpy as np

    from carvi_torch.evaluate import evaluate
    from carvi_torch.reconstruct import main as reconstruct_main
    from carvi_torch.synthetic import procedural

    st = load_tool("studies", "studies_tool")
    procedural.write_default_collection(tmp_path / "set", instances_per_class=6, views_per_instance=2,
                                        categories=["car"], seed=0, progress=False)
    data, recon = tmp_path / "set" / "annotations.json", tmp_path / "recon"
    assert reconstruct_main(["--data", str(data), "--out", str(recon), "--quiet", "stage=cameras"]) == 0
    res = evaluate(data, {"estimated": recon}, shapes=False, progress=False)
    rep = res["viewpoints"]["car"]["estimated"]["refined"]
    model = {a["id"]: a["source"] for a in json.loads(data.read_text())["annotations"]}
    expected: dict = {}
    for a, e in zip(rep["annotation_ids"], rep["per_instance_geodesic"]):
        expected.setdefault(model[a], []).append(e)
    out = tmp_path / "records.json"
    out.write_text(json.dumps({"other": {"command": "kept"}}))
    assert st.main(["misses", "--data", str(data), "--out", str(out), "--key", "k"]) == 0
    records = json.loads(out.read_text())
    assert records["other"] == {"command": "kept"}
    per_model = records["k"]["sets"]["set"]["car"]
    assert sorted(per_model) == sorted(expected) and len(per_model) == 6
    for m, r in per_model.items():
        assert r["n"] == 2 and r["final_deg"][1] == pytest.approx(np.median(expected[m]), abs=0.02), m
        assert r["final_deg"][0] == pytest.approx(min(expected[m]), abs=0.02), m
        assert max(r["true_deg"]) < 1e-2, m  # R_gt G^T, scored under G: the truth itself
        e = r["energy"]
        assert e["true_refined"] <= e["true"] * (1 + 1e-6), m
        assert 0 <= min(r["hull"].values()) and max(r["hull"].values()) <= 1, m
        assert set(r["energy"]) == {"final", "true", "true_refined", "mirror"}, m


def test_benchmark_compares_the_class_folders_byte_for_byte(tmp_path):
    """``differing_outputs``: the class folders' files (those beside a ``cameras.json``) compared byte for byte;
    the run's own records ignored; a changed byte, a missing file and an extra file each listed."""
    bm = load_tool("benchmark", "benchmark_tool")
    for run in ("a", "b"):
        for rel, data in {"car/cameras.json": b"{}", "car/voxels/1.npz": b"x1", "car/meshes/1.ply": b"m",
                          "summary.json": run.encode(), "run.log": run.encode()}.items():
            (tmp_path / run / rel).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / run / rel).write_bytes(data)
    a, b = tmp_path / "a", tmp_path / "b"
    assert bm.differing_outputs(a, b) == []
    (b / "car/voxels/1.npz").write_bytes(b"x2")
    (b / "car/voxels/2.npz").write_bytes(b"y")
    (a / "car/meshes/1.ply").unlink()
    assert bm.differing_outputs(a, b) == ["car/meshes/1.ply", "car/voxels/1.npz", "car/voxels/2.npz"]


def test_benchmark_variants_take_turns_round_by_round(tmp_path, monkeypatch):
    """``take_turns``: each variant once a round, in their order in even rounds and in reverse in odd ones, at
    least one round; the many-class runs go through it (with ``--compare-with`` and ``--compare-set``: new, old,
    alt, then alt, old, new) and their record keeps each variant's rounds in order, the best round and the ratios
    taken from them."""
    import argparse
    import doctest

    bm = load_tool("benchmark", "benchmark_tool")
    assert doctest.testmod(bm).failed == 0  # take_turns' example
    calls = []
    turns = bm.take_turns({k: (lambda k=k: calls.append(k) or len(calls)) for k in "abc"}, 0)
    assert calls == ["a", "b", "c"] and turns == {"a": [1], "b": [2], "c": [3]}
    calls.clear()
    turns = bm.take_turns({k: (lambda k=k: calls.append(k) or len(calls)) for k in "abc"}, 4)
    assert calls == list("abccbaabccba") and list(turns) == ["a", "b", "c"]
    assert turns["a"] == [1, 6, 7, 12] and turns["c"] == [3, 4, 9, 10]

    order = []

    def fake_run_many(data, out, args, name, sets, path):
        order.append(name)
        return {"name": name, "sets": sets, "wall_seconds_with_startup": float(len(order)), "total_seconds": 1.0}

    monkeypatch.setattr(bm, "ensure_many_classes", lambda data_dir, seed: tmp_path / "annotations.json")
    monkeypatch.setattr(bm, "run_many", fake_run_many)
    monkeypatch.setattr(bm, "differing_outputs", lambda a, b: [])
    args = argparse.Namespace(data_dir=str(tmp_path), seed=0, compare_with=str(tmp_path), compare_set=["x=1"],
                              rounds=2, work_dir=str(tmp_path / "runs"))
    m = bm.many_classes(args, bm.torch.device("cpu"))
    assert order == ["new", "old", "alt", "alt", "old", "new"]
    assert {k: [r["wall_seconds_with_startup"] for r in v] for k, v in m["runs"].items()} == {
        "new": [1.0, 6.0], "old": [2.0, 5.0], "alt": [3.0, 4.0]}
    assert m["runs"]["alt"][0]["sets"] == ["x=1"] and m["best"]["old"]["wall_seconds_with_startup"] == 2.0
    assert m["new_over"]["alt"]["wall_seconds_with_startup"]["per_round"] == [1 / 3, 6 / 4]


def test_benchmark_load_only_times_the_loading_and_the_resampling_on_the_same_canvases(procedural_input, tmp_path):
    """``--load-only``: the loading timed ``--repeat`` times; the resampling alone by the batched op and the
    per-object reference, both checked against the loaded canvases."""
    import argparse

    bm = load_tool("benchmark", "benchmark_tool")
    data = procedural_input(tmp_path)
    lo = bm.time_loading(data, argparse.Namespace(objects=6, category="car", repeat=2))
    assert lo["objects"] == 6 and len(lo["seconds"]["one thread"]) == 2
    assert lo["best_seconds"]["one thread"] == min(lo["seconds"]["one thread"])
    rs = lo["resampling"]
    assert rs["same_canvases"] is True and all(len(v) == 2 for v in rs["seconds"].values())
    assert rs["batched_over_reference"] == min(rs["seconds"]["batched"]) / min(rs["seconds"]["reference"])
    table = bm._loading_table(lo).splitlines()
    assert table[0].endswith("| one thread |") and table[3].startswith("| objects per second |")
    assert "per-object reference" in table[-1] and table[-1].endswith("the same canvases: True")

    # a canvas that differs from the loaded one is reported, not hidden
    from dataclasses import replace

    from carvi_torch.io.coco import load_coco
    coll = load_coco(data, canvas_size=32, classes=["car"]).collections["car"]
    assert bm.time_resampling(data, coll, 32, 1)["same_canvases"] is True
    bad = coll.masks.clone()
    bad[0, 0, 0] = ~bad[0, 0, 0]
    assert bm.time_resampling(data, replace(coll, masks=bad), 32, 1)["same_canvases"] is False


def test_benchmark_end_to_end_counts_the_loading(tmp_path, monkeypatch):
    """summary.json's ``total_seconds`` starts after the annotations are read: the end-to-end figure adds
    ``load_seconds``, and the main process's "other" time is what the stages of the main process leave of it
    (the writers' stages overlap and do not count)."""
    import argparse

    bm = load_tool("benchmark", "benchmark_tool")
    out = tmp_path / "run"
    summary = {"total_seconds": 10.0, "load_seconds": 3.0, "peak_rss_mb": 100.0, "writer_workers": 1,
               "peak_rss_workers_mb": 50.0, "classes": {"car": {"objects": 4, "reconstructed": 4, "skipped": [],
                                                                "seconds": {"sfm": 2.0, "carve": 5.0, "write": 9.0}}}}

    def fake_run(cmd, **kw):
        out.mkdir()
        (out / "summary.json").write_text(json.dumps(summary))
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(bm.subprocess, "run", fake_run)
    args = argparse.Namespace(device="cpu", resolution=60, proposals=20, category="car", set=[], threads=None,
                              workers=None)
    e2e = bm.run_end_to_end(tmp_path / "a.json", out, args)
    assert e2e["end_to_end_seconds"] == 13.0 and e2e["total_seconds"] == 10.0
    assert e2e["other_main_seconds"] == pytest.approx(13.0 - 3.0 - 2.0 - 5.0)
    assert e2e["objects_per_second"] == pytest.approx(4 / 13.0)
    assert any("loading included" in line and "| 13.0 |" in line for line in bm._e2e_table(e2e))


def test_benchmark_times_writing_with_and_without_fsync(tmp_path, monkeypatch):
    """The writing comparison flushes every file of the ``sync`` turns and none of the others, checks trimesh's
    cache on hashlib in the ``hashlib checks`` turns alone (and puts its hash back), times the quality signal's two
    projections (which agree), and leaves nothing behind in its work folder."""
    import os

    import trimesh.caching

    bm = load_tool("benchmark", "benchmark_tool")
    fast, hashed = trimesh.caching.hash_fast, []
    monkeypatch.setattr(trimesh.caching, "hash_fallback", lambda b: hashed.append(len(b)) or 7)
    vox = tmp_path / "run" / "car" / "voxels"
    vox.mkdir(parents=True)
    for i in range(3):
        occ = np.zeros((10, 10, 10), bool)
        occ[2:7, 3:8, 2 + i:6 + i] = True
        np.savez(vox / f"{i}.npz", occupancy=occ, voxel_to_camera=np.eye(4),
                 voxel_to_canvas=np.eye(4)[[2, 1, 0, 3]] * [[3.0], [2.0], [1.0], [1.0]])
    synced, real_fsync = [], os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    wr = bm.time_writing(tmp_path / "run", objects=5, repeat=2, work=tmp_path / "w")
    assert wr["objects"] == 3 and len(synced) == 2 * 3 * 2  # 2 sync turns x 3 objects x 2 files
    assert set(wr["seconds"]) == {"sync", "no sync", "hashlib checks"} and all(len(v) == 2
                                                                            for v in wr["seconds"].values())
    assert wr["no_sync_over_sync"] == wr["ms_per_object"]["no sync"] / wr["ms_per_object"]["sync"]
    assert wr["xxhash_over_hashlib"] == wr["ms_per_object"]["no sync"] / wr["ms_per_object"]["hashlib checks"]
    assert hashed and trimesh.caching.hash_fast is fast  # the fallback hashed the meshes of its turns; put back
    iou = wr["reconstruction_iou"]
    assert iou["same"] and iou["per_line_over_general"] == iou["ms_per_object"]["per line"] / iou["ms_per_object"][
        "general"]
    assert not (tmp_path / "w").exists()
    assert "flushed (fsync)" in bm.table({"writing": wr}) and "against hashlib's blake2b" in bm.table({"writing": wr})


def test_train_example_with_too_few_objects_says_so(tmp_path, capsys):
    """``--min-quality`` that keeps fewer than two objects (none to train on, or none to validate on) is one
    ``error:`` line and exit status 2, not a traceback."""
    from carvi_torch.export.store import StoreWriter

    writer = StoreWriter(tmp_path / "exp", shard_size=2, fields=["mask", "viewpoint", "class_index", "quality"])
    for i, q in enumerate((0.1, 0.5, 0.9)):
        writer.add("car", {"mask": np.zeros((8, 8), bool), "viewpoint": np.zeros(3, np.float32),
                           "class_index": np.int64(0), "quality": np.float32(q)},
                   {"annotation_id": i + 1, "image_id": i + 1, "source": ""})
    writer.close({"classes": ["car"]})
    train = load_tool("train_example")
    for cut, kept in (("0.95", 0), ("0.8", 1)):
        capsys.readouterr()
        assert train.main(["--export", str(tmp_path / "exp"), "--min-quality", cut, "--epochs", "1",
                           "--workers", "0"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and f"keeps {kept} of 3 object(s)" in err[0], err


def test_bench_viewpoints_times_the_mixture_fit_on_a_small_class(tmp_path: Path, capsys):
    """``bench_viewpoints --groups 2`` hands the mixture fit the masks it reads and records the fit, the groups'
    refinement and the stage with the mixture; ``--one-thread-too`` checks that one thread gives the same fit."""
    bv = load_tool("bench_viewpoints")
    out = tmp_path / "viewpoints.json"
    rec = bv.main(["--n", "30", "--k", "10", "--canvas", "48", "--max-outer", "10", "--max-iters", "5", "--groups", "2",
                   "--one-thread-too", "--group-threads", "2", "--threads-min-objects", "0", "--out", str(out)])
    assert json.loads(out.read_text())["config"]["with_mirrors"] == 60
    mix = rec["mixture_fit"]
    assert mix["warm"]["groups"] >= 1 and sum(mix["warm"]["sizes"]) <= 30
    assert mix["warm"]["stage_seconds"] > mix["warm"]["seconds"] > 0 and mix["warm"]["refinement_seconds"] > 0
    assert mix["threads_same_result"] is True
    assert "stage with mixture" in capsys.readouterr().out


def test_bench_viewpoints_runs_sfm_with_the_pipelines_settings(tmp_path: Path):
    """The tool's SfM and the mixture's group SfMs take the pipeline's polish, rounds, tolerance and compiled
    factorisation (the config's defaults, or ``--set``), with its own ``--max-outer`` and ``--inner``."""
    from carvi_torch.config import Config

    bv = load_tool("bench_viewpoints")
    default = Config().viewpoints
    args = bv.build_parser().parse_args(["--max-outer", "7"])
    opts = bv.sfm_options(args, Config().override(args.set).viewpoints)
    assert (opts.polish, opts.polish_iters, opts.tol, opts.native, opts.max_outer) == (
        default.sfm_polish, default.sfm_polish_iters, default.sfm_tol, default.sfm_native, 7)
    args = bv.build_parser().parse_args(["--set", "viewpoints.sfm_polish=alternate", "viewpoints.sfm_polish_iters=30",
                                         "viewpoints.sfm_native=false"])
    opts = bv.sfm_options(args, Config().override(args.set).viewpoints)
    assert (opts.polish, opts.polish_iters, opts.native) == ("alternate", 30, False)
    assert (opts.max_outer, opts.inner) == (default.sfm_max_outer, default.sfm_inner)
    # the config's outer and inner steps reach SfM too (``--max-outer`` and ``--inner`` win where given)
    args = bv.build_parser().parse_args(["--set", "viewpoints.sfm_max_outer=7", "viewpoints.sfm_inner=3"])
    opts = bv.sfm_options(args, Config().override(args.set).viewpoints)
    assert (opts.max_outer, opts.inner) == (7, 3)
    out = tmp_path / "viewpoints.json"
    rec = bv.main(["--n", "20", "--k", "10", "--canvas", "48", "--max-outer", "10", "--max-iters", "5",
                   "--set", "viewpoints.sfm_polish=alternate", "--out", str(out)])
    assert rec["config"]["sfm_options"]["polish"] == "alternate"
    assert json.loads(out.read_text())["config"]["sfm_options"]["max_outer"] == 10


def test_train_example_refuses_an_export_that_is_not_there(tmp_path, monkeypatch, capsys):
    """``--export`` naming a folder without an export (a typo) is one ``error:`` line and exit status 2; it does
    not reconstruct and export the embedded collection beside it instead (minutes of work, outside what was
    asked)."""
    train = load_tool("train_example")
    built = []
    monkeypatch.setattr(train, "_build_export", built.append)
    capsys.readouterr()
    assert train.main(["--export", str(tmp_path / "exprot"), "--epochs", "1", "--workers", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert built == [] and len(err) == 1 and err[0].startswith("error: --export "), err
    assert list(tmp_path.iterdir()) == []


def test_train_example_help_gives_every_default(capsys):
    train = load_tool("train_example")
    text = " ".join(train.build_parser().format_help().split())
    for option, default in (("--epochs", "8"), ("--batch-size", "32"), ("--workers", "2"), ("--seed", "0")):
        assert f"{option} {option[2:].upper().replace('-', '_')} " in text
        assert f"(default {default}" in text.split(f"{option} {option[2:].upper().replace('-', '_')} ", 1)[1][:200]


def test_train_example_reads_a_format_one_export_it_is_given(tmp_path, monkeypatch, capsys):
    """``--export`` naming a format-1 export (``index.json``, no ``zarr.json``) is read as it is: the example
    neither reconstructs the embedded collection beside it nor exports into it."""
    train = load_tool("train_example")
    built, opened = [], []

    class Empty:
        reader = SimpleNamespace(samples=[])

        def __init__(self, root, **kw):
            opened.append(Path(root))

        def __len__(self):
            return 0

    monkeypatch.setattr(train, "_build_export", built.append)
    monkeypatch.setattr(train, "LiftedDataset", Empty)
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "index.json").write_text("{}")
    assert train.main(["--export", str(tmp_path / "old"), "--epochs", "1", "--workers", "0"]) == 2
    assert built == [] and opened == [tmp_path / "old"]
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["index.json", "old"]


def test_viewpoints_cad_change_over_seeds_draws_models_across_the_seeds(tmp_path: Path):
    """The seeds table's last column: median_change over both seeds' views with a view's CAD model as its cluster
    and its seed as its run, read from each seed's cameras.json, gt.json and annotations.json; a view without an
    SfM camera is left out."""
    import torch

    from carvi_torch.cameras import random_rotations
    from carvi_torch.evaluation.viewpoint_metrics import median_change

    vc = load_tool("viewpoints_cad")
    g = torch.Generator().manual_seed(3)
    runs, want = [], []
    for seed in (0, 1):
        R = random_rotations(3 * 6, g, dtype=torch.float64).reshape(3, 6, 3, 3)
        renders, recon = tmp_path / f"renders{seed}", tmp_path / f"recon{seed}"
        (recon / "thing").mkdir(parents=True)
        renders.mkdir()
        anns = [{"id": i, "source": f"thing0{i % 3}.npz"} for i in range(6)]
        (renders / "annotations.json").write_text(json.dumps({"annotations": anns}))
        (renders / "gt.json").write_text(json.dumps({"annotations": {str(i): {"R": R[2, i].tolist()}
                                                                     for i in range(6)}}))
        cams = {str(i): {"sfm": {"R": R[0, i].tolist()}, "refined": {"R": R[1, i].tolist()}} for i in range(6)}
        cams["4"]["sfm"] = None
        (recon / "thing" / "cameras.json").write_text(json.dumps({"cameras": cams}))
        runs.append({"seed": seed, "renders": renders, "recon": recon, "rows": [{"class": "thing"}]})
        want += [(R[0, i], R[1, i], R[2, i], f"thing0{i % 3}", seed) for i in range(6) if i != 4]
    got = vc._change_over_seeds(runs)["thing"]
    ref = median_change(*(torch.stack([w[k] for w in want]) for k in range(3)), [w[3] for w in want],
                        runs=[w[4] for w in want])
    assert (got["objects"], got["clusters"], got["runs"]) == (10, 3, 2)
    assert (got["change"], got["low"], got["high"]) == pytest.approx((ref["change"], ref["low"], ref["high"]),
                                                                    abs=1e-3)
    from carvi_torch.evaluate import format_change

    for run in runs:  # the seed table's rows, as _rows makes them: its last column is the change over the seeds
        run["rows"][0].update(sfm_geodesic=5.0, refined_geodesic_sfm_objects=5.5, kept_sfm=0,
                              change_from_sfm={"change": 0.5, "low": 0.1, "high": 0.9})
    table, per_class = vc._seeds_table(runs)
    line = next(t for t in table.splitlines() if t.startswith("| thing |"))
    assert line.endswith(f"| seed 0, 1 | {format_change(got)} |") and per_class["thing"]["change_over_seeds"] == got


def test_voc_study_refinement_change_uses_the_objects_with_both_cameras():
    """The SfM -> refined change of the VOC study is median_change on exactly the objects with an SfM camera, a
    refined one and ground truth, in one order, each annotation its own object."""
    import torch

    from carvi_torch.cameras import random_rotations
    from carvi_torch.evaluation.viewpoint_metrics import median_change

    vs = load_tool("voc_study")
    g = torch.Generator().manual_seed(0)
    R = random_rotations(3 * 8, g, dtype=torch.float64).reshape(3, 8, 3, 3)
    cams = {str(i): {"source": f"2008_{i:06d}_1.xml", "sfm": {"R": R[0, i].tolist()},
                     "refined": {"R": R[1, i].tolist()}} for i in range(8)}
    cams["0"]["sfm"] = None  # no SfM camera: left out
    cams["5"]["refined"] = None  # no refined camera: left out
    gt = {f"2008_{i:06d}_1": {"R": R[2, i].tolist()} for i in range(8) if i != 3}  # no truth for 3
    got = vs._refinement_change(cams, gt)
    keep = [1, 2, 4, 6, 7]
    want = median_change(R[0, keep], R[1, keep], R[2, keep])
    assert got["objects"] == got["clusters"] == 5
    assert (got["change"], got["low"], got["high"]) == pytest.approx((want["change"], want["low"], want["high"]),
                                                                    abs=1e-3)
    cams["6"]["refined"]["R"] = cams["6"]["sfm"]["R"]  # one object unchanged by refinement: another change
    assert vs._refinement_change(cams, gt)["change"] != pytest.approx(got["change"], abs=1e-3)


def test_voc_study_paired_comparison_known_values():
    vs = load_tool("voc_study")
    a = np.array([1.0, 4.0, 2.0, 8.0, 5.0])
    shifted = vs.paired_comparison(a, a + 1.5)  # every object 1.5 closer under a: every resample says -1.5
    assert shifted["difference"] == -1.5 and shifted["interval_95"] == [-1.5, -1.5]
    assert (shifted["a_lower"], shifted["b_lower"]) == (5, 0)
    assert shifted["sign_test_p"] == pytest.approx(2 * 0.5 ** 5)  # two-sided, all five one way
    same = vs.paired_comparison(a, a.copy())
    assert same["difference"] == 0.0 and same["interval_95"] == [0.0, 0.0]
    assert (same["a_lower"], same["b_lower"], same["sign_test_p"]) == (0, 0, 1.0)
    assert same["median_a"] == same["median_b"] == 4.0


def test_voc_study_paired_comparison_against_a_brute_force_sign_test_and_bootstrap():
    from math import comb

    vs = load_tool("voc_study")
    gen = np.random.default_rng(3)
    a = gen.random(10)
    b = a + np.where(np.arange(10) < 7, 0.1, -0.1)  # a closer for 7 objects, b for 3
    r = vs.paired_comparison(a, b, resamples=300, seed=5)
    assert (r["a_lower"], r["b_lower"]) == (7, 3)
    assert r["sign_test_p"] == pytest.approx(2 * sum(comb(10, k) for k in range(7, 11)) / 2 ** 10)  # 0.34375
    draws = np.random.default_rng(5).integers(0, 10, (300, 10))
    loop = [np.median(a[d]) - np.median(b[d]) for d in draws]  # one resample at a time
    assert r["interval_95"] == pytest.approx([np.percentile(loop, 2.5), np.percentile(loop, 97.5)])
    assert r == vs.paired_comparison(a, b, resamples=300, seed=5)  # same seed, same interval
    with pytest.raises(ValueError, match="equal"):
        vs.paired_comparison(a, b[:9])


def test_voc_study_compare_set_needs_cameras_only(tmp_path: Path):
    vs = load_tool("voc_study")
    data = tmp_path / "data" / "pascal_voc_aeroplane"
    (data / "keypoints").mkdir(parents=True)
    (data / "viewpoints_dev.json").write_text("{}")
    with pytest.raises(SystemExit, match="--compare-set needs --cameras-only"):
        vs.main(["--data", str(tmp_path / "data"), "--work", str(tmp_path / "work"), "--compare-set", "refine=false"])


def test_voc_study_doctests_run():
    import doctest

    result = doctest.testmod(load_tool("voc_study"), verbose=False)  # paired_comparison's example among them
    assert result.attempted >= 2 and result.failed == 0


def test_bench_viewpoints_kernels_compares_both_paths_per_class(tmp_path: Path, procedural_input):
    """``bench_viewpoints --kernels``: per class of the embedded collection the compiled bundle adjustment takes
    the torch path's damped solves and ends within 1e-6 degrees of it, and the batched hull agreements equal the
    reference's; the table and the record say so."""
    from carvi_torch import native_library

    if native_library.library_operators() is None:
        pytest.skip(f"no compiled kernel here: {native_library.load()['reason']}")
    bv = load_tool("bench_viewpoints")
    data = procedural_input(tmp_path)
    out = tmp_path / "k.json"
    rec = bv.main(["--kernels", str(data), "--rounds", "1", "--out", str(out), "--key", "k"])
    assert json.loads(out.read_text())["k"]["classes"].keys() == rec["classes"].keys() and len(rec["classes"]) >= 2
    for name, r in rec["classes"].items():
        assert r["solves"][0] == r["solves"][1] >= 1, name
        assert r["bundle_max_angle_deg"] < 1e-6 and r["hull_equal"] and r["hull_rows"] > 0, name
        assert min(r["bundle_ms_per_solve"].values()) > 0, name


def test_gpu_session_packs_what_a_lease_carries(tmp_path: Path):
    """``--pack`` (wheels off: no network in tests) copies ../shared/data and the steps' inputs that are there into
    .gpu_shared/, skips those that are not, and prints the ``run`` call that carries .whl and .gpu_shared."""
    work = tmp_path / "repo"
    (tmp_path / "shared" / "data" / "pascal3d_cad").mkdir(parents=True)
    (tmp_path / "shared" / "data" / "pascal3d_cad" / "car01.npz").write_bytes(b"x")
    car = work / "outputs" / "bench" / "data" / "car1000_s0"
    car.mkdir(parents=True)
    for name in ("annotations.json", "gt.json"):
        (car / name).write_text("{}")
    (car / "meshes").mkdir()  # not carried: the steps read the JSON files only
    res = subprocess.run(["bash", str(GPU_SESSION), "--pack"], cwd=work, env=dict(os.environ, PACK_WHEELS=""),
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    packed = sorted(p.relative_to(work / ".gpu_shared").as_posix() for p in (work / ".gpu_shared").rglob("*")
                    if p.is_file())
    assert packed == ["data/pascal3d_cad/car01.npz", "outputs/bench/data/car1000_s0/annotations.json",
                      "outputs/bench/data/car1000_s0/gt.json"]
    assert not (work / ".whl").exists()
    assert 'run(carry=[".whl", ".gpu_shared"]' in res.stdout and "gpu_session.sh lease /tmp/gpu" in res.stdout


def _script_list(name: str) -> list[str]:
    """The names of one of the GPU script's package lists (``NAME="..."``)."""
    import re

    return re.search(rf'^{name}="([^"]*)"', GPU_SESSION.read_text(), flags=re.M).group(1).split()


def _requirement_key(req: str) -> str:
    import re

    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9._-]+", req).group()).lower()


def test_gpu_session_packs_the_wheels_of_pyprojects_requirements(tmp_path: Path):
    """``--pack`` downloads pyproject.toml's dependencies and test extra as written there, less those the lent
    image has (IMAGE_HAS) and those whose tests skip without them (NOT_CARRIED), and the dependencies of theirs
    the image lacked (ALSO_CARRIED); a dependency added to pyproject.toml is packed with no other change, and each
    name the script keeps names a requirement of pyproject.toml."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11 or later, as the script's reading of pyproject.toml

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    reqs = project["dependencies"] + project["optional-dependencies"]["test"]
    image, skip, also = _script_list("IMAGE_HAS"), _script_list("NOT_CARRIED"), _script_list("ALSO_CARRIED")
    keys = {_requirement_key(r) for r in reqs}
    assert {_requirement_key(n) for n in image + skip} <= keys and not keys & {_requirement_key(n) for n in also}
    repo = tmp_path / "repo"
    (repo / "tools").mkdir(parents=True)
    (repo / "tools" / "gpu_session.sh").write_text(GPU_SESSION.read_text())
    added = "dependencies = [\n    'carvi-new-dep>=1.2',\n"  # a dependency pyproject.toml gains
    (repo / "pyproject.toml").write_text((ROOT / "pyproject.toml").read_text().replace("dependencies = [\n", added, 1))
    log = tmp_path / "pip.json"
    fake = tmp_path / "python"  # records what pip would download; anything else runs on this interpreter
    fake.write_text(f"""#!{sys.executable}
import json, os, sys
if sys.argv[1:4] == ["-m", "pip", "download"]:
    json.dump(sys.argv[sys.argv.index("-d") + 2:], open({str(log)!r}, "w"))
    sys.exit(0)
os.execv(sys.executable, [sys.executable, *sys.argv[1:]])
""")
    fake.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "PACK_WHEELS"}
    res = subprocess.run(["bash", "tools/gpu_session.sh", "--pack"], cwd=repo, env=dict(env, PYTHON=str(fake)),
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    left_out = {_requirement_key(n) for n in image + skip}
    expected = ["carvi-new-dep>=1.2"] + [r for r in reqs if _requirement_key(r) not in left_out] + also
    assert json.loads(log.read_text()) == expected
    assert "kornia>=0.9" in expected and not any(_requirement_key(r) == "torch" for r in expected)


def test_gpu_session_installs_the_wheels_when_a_requirement_does_not_import(tmp_path: Path):
    """On the lent machine the script imports each of pyproject.toml's requirements (PyYAML as yaml, Pillow as
    PIL; NOT_CARRIED's left out) and installs the carried wheels when one fails, else goes on to the device."""
    repo, stubs = tmp_path / "repo", tmp_path / "stubs"
    (repo / "tools").mkdir(parents=True)
    (repo / ".whl").mkdir()
    (repo / ".whl" / "carried-1.0-py3-none-any.whl").write_bytes(b"")
    (repo / "tools" / "gpu_session.sh").write_text(GPU_SESSION.read_text())
    (repo / "pyproject.toml").write_text('[project]\nname = "p"\ndependencies = ["PyYAML>=6.0", "Pillow>=9.0"]\n'
                                         '[project.optional-dependencies]\ntest = ["ray>=2.9"]\n')
    stubs.mkdir()
    (stubs / "ray.py").write_text("raise ImportError('not carried')\n")  # a NOT_CARRIED one fails: not checked
    log = tmp_path / "calls.txt"
    fake = tmp_path / "python"  # the package check on this interpreter; every other call fails and is logged
    fake.write_text(f'#!/bin/sh\n[ "$3" = check ] && exec "{sys.executable}" "$@"\necho "$@" >> "{log}"\nexit 1\n')
    fake.chmod(0o755)

    def run() -> tuple[int, str]:
        log.write_text("")
        res = subprocess.run(["bash", "tools/gpu_session.sh", "tests", str(tmp_path / "out")], cwd=repo,
                             env=dict(os.environ, PYTHON=str(fake), PYTHONPATH=str(stubs)), capture_output=True,
                             text=True, timeout=60)
        return res.returncode, log.read_text()

    rc, calls = run()
    assert rc == 2 and "pip install" not in calls and "cuda.is_available" in calls, calls
    (stubs / "yaml.py").write_text("raise ImportError('not installed')\n")
    rc, calls = run()
    assert rc == 1 and "pip install" in calls and "carried-1.0-py3-none-any.whl" in calls, calls



def _run_with_meshes(run: Path, cls: str, meshes: dict, mesh_format: str) -> None:
    """A run folder ``run`` whose ``config.yaml`` says ``mesh.format=mesh_format``, with class ``cls``'s meshes
    ``meshes`` (file name -> trimesh) and a refined camera (identity, scale 1) for every object named."""
    from carvi_torch.config import Config

    (run / cls / "meshes").mkdir(parents=True)
    (run / "config.yaml").write_text(Config().override({"mesh.format": mesh_format}).to_yaml())
    cams = {}
    for name, mesh in meshes.items():
        mesh.export(run / cls / "meshes" / name)
        cams[name.split(".")[0]] = {"refined": {"R": np.eye(3).tolist(), "s": 1.0, "t": [0.0, 0.0]}}
    (run / cls / "cameras.json").write_text(json.dumps({"cameras": cams}))


def test_studies_clusters_read_the_meshes_of_a_run_in_its_mesh_format(tmp_path: Path, monkeypatch):
    """``studies.py clusters`` takes a run's meshes in the format its ``config.yaml`` names (obj here), not .ply
    alone: every object with a mesh and a refined camera is clustered."""
    import argparse

    import trimesh

    st = load_tool("studies", "studies_tool")
    bench = tmp_path / "bench"
    data = bench / "data_pool1_test0_seed0"
    data.mkdir(parents=True)
    (data / "annotations.json").write_text(json.dumps({"annotations": [{"id": i, "source": f"m{i % 2}"}
                                                                      for i in range(4)]}))
    _run_with_meshes(bench / "run_full", "thing",
                     {f"{i}.obj": trimesh.creation.box(extents=(1.0 + i, 1.0, 1.0)) for i in range(4)}, "obj")
    record, drawn = tmp_path / "clusters.json", {}
    monkeypatch.setattr(st, "_record", lambda name: record)
    monkeypatch.setattr(st, "_plot_clusters", lambda figs, k: drawn.update(figs))
    assert st.clusters(argparse.Namespace(bench=str(bench), k=2, points=64, seed=0)) == 0
    thing = json.loads(record.read_text())["classes"]["thing"]
    assert thing["objects"] == 4 and sum(thing["sizes"]) == 4 and len(drawn["thing"]) == 2


def test_voc_study_reads_the_mesh_of_the_runs_mesh_format(tmp_path: Path):
    """voc_study takes a run's meshes through the package's lookup: in the format its ``config.yaml`` names first
    (an older .ply beside it is not the run's), and ``None`` for an object without a mesh."""
    import trimesh

    vs = load_tool("voc_study")
    run = tmp_path / "recon"
    _run_with_meshes(run, vs.CLASS, {"7.obj": trimesh.creation.box(extents=(2.0, 2.0, 2.0)),
                                     "7.ply": trimesh.creation.box(extents=(1.0, 1.0, 1.0))}, "obj")
    fmt = vs.run_mesh_format(run)
    assert fmt == "obj"
    np.testing.assert_allclose(vs._recon_mesh(run, 7, fmt).extents, [2.0, 2.0, 2.0])
    assert vs._recon_mesh(run, 8, fmt) is None


def test_benchmark_make_run_times_the_default_run_step_by_step(tmp_path, monkeypatch):
    """``--make-run``: its child process runs ``make run``'s command with the steps the package still has timed in
    place (a tiny default run here: every step found, the whole process the sum of the steps and ``other``); the
    variants take turns (new with the collection cached, new with an empty cache, old) and the table gives each
    step's median; the runs' files are compared byte for byte but for those holding times or the folder's name."""
    import argparse

    bm = load_tool("benchmark", "benchmark_tool")
    tiny = ["procedural_instances=6", "resolution=16", "proposals=2", "canvas_size=64", "classes=car",
            "report=false", "preview=false"]
    args = argparse.Namespace(set=tiny, work_dir=str(tmp_path), compare_with=None, rounds=1)
    cache = bm._cache_with_kernels(tmp_path / "cache")
    t = bm.make_run_once(tmp_path / "run", cache, args, "new", None)
    assert all(t[k] > 0 for k in ("imports", "collection", "reconstruction", "whole process")), t
    assert abs(sum(t[k] for k in bm.MAKE_RUN_STEPS[:5]) - t["whole process"]) < 0.01
    assert 0 < t["reconstruction (CPU)"] and abs(sum(t[k + " (CPU)"] for k in bm.MAKE_RUN_STEPS[:5])
                                               - t["whole process (CPU)"]) < 0.01
    assert (tmp_path / "run" / "car" / "cameras.json").is_file() and list((cache / "collections").glob("*.npz"))

    seen = []

    def fake_once(out, cache, args, name, pythonpath):
        seen.append((out.name, cache.name, pythonpath))
        out.mkdir(parents=True, exist_ok=True)
        (out / "summary.json").write_text(name)
        return {"load_average": 0.0, **{k + c: float(len(seen)) for k in bm.MAKE_RUN_STEPS for c in ("", " (CPU)")}}

    monkeypatch.setattr(bm, "make_run_once", fake_once)
    args = argparse.Namespace(set=[], work_dir=str(tmp_path / "w"), compare_with=str(tmp_path), rounds=2)
    m = bm.make_run(args)
    assert [s[0] for s in seen] == ["new", "new_first_run", "new", "old", "old", "new", "new_first_run"]
    assert [s[1] for s in seen[1:4]] == ["cache_cold", "cache_warm", "cache_cold"] and seen[3][2] == str(tmp_path)
    assert m["median"]["new"]["imports"] == 4.5 and m["differing_files_from_old"] == {"new, first run": [],
                                                                                      "new": []}
    table = "\n".join(bm._make_run_table(m))
    assert "| imports | 4.50 (4.50) | 4.50 (4.50) | 4.50 (4.50) |" in table and "the same byte for byte" in table
    (tmp_path / "w" / "make_run" / "new" / "preview.png").write_bytes(b"x")
    assert bm.run_files_differing(tmp_path / "w" / "make_run" / "old", tmp_path / "w" / "make_run" / "new") == [
        "preview.png"]
