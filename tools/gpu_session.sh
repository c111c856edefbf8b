#!/usr/bin/env bash
# Everything to run when a CUDA machine is at hand, in one command: the CUDA tests and the GPU
# benchmarks (docs/benchmarks.md; tools/benchmark.py --device cuda), each new path timed against
# the current one in the same run. Run from the repository root:
#
#     bash tools/gpu_session.sh [all|tests|bench1000|bench9087|manyclasses|cad8|lease] [OUTDIR]
#
# OUTDIR defaults to $OUT (the lent machine's result folder) or outputs/gpu; each step writes its
# log and JSON there. Python is $PYTHON or python3, with torch and CUDA. Packages the machine lacks
# travel as wheels in .whl/ (installed once into /tmp/carvi_site, never into the system). The data
# are generated on first use, or carried: outputs/bench/data/car1000_s0/{annotations.json,gt.json}
# (3 MB; the 9,087-object class is tiled from it), outputs/bench/data/cad_v8_s0/annotations.json
# (0.5 MB: the many-class data) and ../shared/data/pascal3d_cad (cad8; CAD=path elsewhere).
#
# Steps (new paths against the current ones in the same run, ratios in OUTDIR/ratios.txt):
#   tests        pytest -m cuda (117 s on an H200 at b9a1ed9)
#   bench1000    tools/benchmark.py --device cuda --objects 1000, the carving comparison included
#   bench9087    the 9,087-object class: its loading with the canvases on one thread and on
#                canvas_threads (--load-only), then mesher=auto (marching cubes batched on the GPU) and
#                mesher=skimage (the writers mesh); H200: 54 s for auto, skimage stopped at 85 s
#   manyclasses  12 classes of about 50 objects, the viewpoint stage on the run's device (default)
#                against viewpoints.device=cpu; one run did not finish in 110 s on the H200 (bba3577)
#   cad8         the 8-view CAD renders' cameras on the CPU and on CUDA, compared object by object
#                (tolerance 0.5 degrees median per class); DEVICES=cuda runs the CUDA side alone
#                against a CPU run already in OUTDIR/cad8, DEVICES= only compares; H200: the CPU
#                80 s, CUDA over 120 s
#   all          tests, bench1000, bench9087 and manyclasses: longer than a lent machine's 10 minutes
#   lease        STEPS="tests:170 bench9087:150 manyclasses:240 cad8:200" (step:seconds): each step
#                under its own limit, OUTDIR's small files packed into PACK (default OUTDIR.tgz)
#                after each, so what finished comes back when a later step runs out of time
set -uo pipefail
if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then  # the comment above
    sed -n '2,/^set /p' "$0" | sed -e '$d' -e 's/^# \{0,1\}//'
    exit 0
fi
step=${1:-all}
out=${2:-${OUT:-outputs/gpu}}
py=${PYTHON:-python3}
mkdir -p "$out"

case "$step" in
    all|tests|bench1000|bench9087|manyclasses|cad8|lease) ;;
    *) echo "unknown step '$step' (all, tests, bench1000, bench9087, manyclasses, cad8, lease)" >&2; exit 2 ;;
esac

if ! "$py" -c "import kornia, trimesh, pycocotools, shapely, scipy, skimage, yaml, tqdm, matplotlib, pytest" \
        2>/dev/null \
        && [ -d .whl ] && compgen -G ".whl/*.whl" >/dev/null; then
    "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target /tmp/carvi_site .whl/*.whl || exit 1
    export PYTHONPATH="/tmp/carvi_site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
else
    export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
fi

# ---- lease: every step under its own time limit, OUTDIR's small files packed after each step
# (the packages above are installed once; each step's own check then finds them)
#     STEPS="tests:170 bench9087:150 manyclasses:240 cad8:200" PACK=$OUT/results.tgz \
#         bash tools/gpu_session.sh lease /tmp/gpu
# A lent machine returns few files and stops a command at its limit: each step runs under
# `timeout` (seconds after the colon), start and end go to OUTDIR/steps.txt, and after each step
# OUTDIR (without meshes, voxels or arrays) is packed into PACK (default OUTDIR.tgz), so what
# finished comes back even when a later step runs out of time.
if [ "$step" = "lease" ]; then
    pack=${PACK:-${out%/}.tgz}
    t0=$(date +%s)
    for s in ${STEPS:-tests:170 bench9087:150 manyclasses:240 cad8:200}; do
        name=${s%%:*}
        limit=${s##*:}
        echo "[$(( $(date +%s) - t0 )) s] start $name (limit $limit s)" | tee -a "$out/steps.txt"
        timeout -k 5 "$limit" bash "$0" "$name" "$out" > "$out/$name.log" 2>&1
        rc=$?
        echo "[$(( $(date +%s) - t0 )) s] end $name, status $rc" | tee -a "$out/steps.txt"
        tar czf "$pack" -C "$out" --exclude=meshes --exclude='*.npz' --exclude='*.npy' --exclude='*.ply' \
            --exclude='*.obj' --exclude='*.zarr' . || exit 1
    done
    exit 0
fi

# ---- begin: small-class CAD benchmark, CPU against CUDA -------------------------------------
#     bash tools/gpu_session.sh cad8 [OUTDIR]
# Renders the PASCAL3D+ CAD models at 8 views per model (seed 2: the trains' template start),
# reconstructs their cameras on the CPU and on CUDA (tools/viewpoints_cad.py, default settings)
# and compares every object's final camera (degrees between the two), which start each class's
# SfM kept and which camera each object kept (camera_choice). Needs ../shared/data/pascal3d_cad
# (or CAD=path). Tolerance (docs/viewpoints.md): median angle <= 0.5 degrees per class.
# DEVICES=cuda runs the CUDA side alone, against CPU cameras already in OUTDIR/cad8 (an earlier run's);
# DEVICES= (empty) only compares the runs there. A class the CUDA run did not reach is listed as such.
# Per class it also prints the viewpoint stages' seconds on each device (SfM with the mixture's fit,
# refinement: summary.json), and writes all of it to OUTDIR/cad8_agreement.json.
if [ "$step" = "cad8" ]; then
    cad=${CAD:-../shared/data/pascal3d_cad}
    status=0
    for dev in ${DEVICES-cpu cuda}; do
        "$py" tools/viewpoints_cad.py --views 8 --seed 2 --quiet --cad "$cad" --work "$out/cad8" \
            --out "$out/cad8_$dev.json" "device=$dev" 2>&1 | tee "$out/cad8_$dev.txt" || status=1
    done
    "$py" - "$out/cad8" "$out/cad8_agreement.json" <<'PYEOF' 2>&1 | tee "$out/cad8_agreement.txt" || status=1
import json, sys
from pathlib import Path
import numpy as np
import torch
from carvi_torch.cameras import geodesic_angle
work, worst, rows = Path(sys.argv[1]), 0.0, {}
runs = {d: work / f"cameras_device-{d}_v8_renders-s2" for d in ("cpu", "cuda")}
summ = {d: json.loads((p / "summary.json").read_text())["classes"] for d, p in runs.items()}
seconds = lambda d, cls: round(sum(summ[d][cls]["seconds"].get(k, 0.0) for k in ("sfm", "refine")), 2)
for cls in sorted(summ["cpu"]):
    if cls not in summ["cuda"] or not (runs["cuda"] / cls / "cameras.json").is_file():
        print(f"{cls:12s} not reached by the CUDA run")
        continue
    cams = {d: json.loads((p / cls / "cameras.json").read_text())["cameras"] for d, p in runs.items()}
    both = [a for a, c in cams["cpu"].items() if c.get("refined") and cams["cuda"].get(a, {}).get("refined")]
    R = [torch.tensor([cams[d][a]["refined"]["R"] for a in both], dtype=torch.float64) for d in ("cpu", "cuda")]
    ang = torch.rad2deg(geodesic_angle(*R)).tolist() if both else []
    choice = sum(c.get("camera_choice") != cams["cuda"].get(a, {}).get("camera_choice") for a, c in cams["cpu"].items())
    start = [summ[d][cls].get("sfm", {}).get("start", {}).get("kept") for d in ("cpu", "cuda")]
    groups = [summ[d][cls].get("sfm_groups", {}).get("groups", 1) for d in ("cpu", "cuda")]
    if not ang:
        print(f"{cls:12s} no object with a refined camera on both devices")
        continue
    med = float(np.median(ang))
    worst = max(worst, med)
    rows[cls] = {"objects": summ["cpu"][cls]["objects"], "compared": len(ang), "median_deg": round(med, 3),
                 "max_deg": round(max(ang), 3), "camera_choice_differs": choice,
                 "sfm_start": start, "shape_groups": groups,
                 "viewpoint_seconds": {"cpu": seconds("cpu", cls), "cuda": seconds("cuda", cls)}}
    print(f"{cls:12s} median {med:.3f} deg, max {rows[cls]['max_deg']:.2f} deg, camera_choice differs in {choice}, "
          f"SfM start cpu/cuda {start[0]}/{start[1]}, shape groups {groups[0]}/{groups[1]}, "
          f"SfM + refinement {seconds('cpu', cls):.1f} s cpu, {seconds('cuda', cls):.1f} s cuda")
cpu_s, cuda_s = (sum(r["viewpoint_seconds"][d] for r in rows.values()) for d in ("cpu", "cuda"))
threads = json.loads((runs["cpu"] / "summary.json").read_text()).get("torch_threads")
print(f"{len(rows)} classes compared; SfM + refinement {cpu_s:.1f} s on the CPU ({threads} torch threads), "
      f"{cuda_s:.1f} s on CUDA")
print(f"largest class median {worst:.3f} deg: {'within' if worst <= 0.5 else 'OUTSIDE'} the 0.5 degree tolerance")
Path(sys.argv[2]).write_text(json.dumps({"classes": rows, "viewpoint_seconds": {"cpu": round(cpu_s, 2),
                                         "cuda": round(cuda_s, 2)}, "largest_median_deg": round(worst, 3)}, indent=1))
sys.exit(0 if rows and worst <= 0.5 else 1)
PYEOF
    echo "results in $out"
    exit "$status"
fi
# ---- end: small-class CAD benchmark, CPU against CUDA ---------------------------------------


if ! "$py" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    echo "no CUDA device visible to $py: nothing to do here" >&2
    exit 2
fi
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null
  "$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"; } | tee "$out/device.txt"

run_tests() {
    # pycolmap is only needed by the rotation cross-checks, which have no CUDA test
    local ignore=()
    "$py" -c "import pycolmap" 2>/dev/null || ignore=(--ignore tests/test_cameras.py)
    # a test module that cannot be imported still fails the step, without stopping the others
    "$py" -m pytest -q -rs -m cuda --continue-on-collection-errors ${ignore[@]+"${ignore[@]}"} tests 2>&1 \
        | tee "$out/pytest_cuda.txt"
    return "${PIPESTATUS[0]}"
}

bench() {  # objects, extra arguments
    local n=$1
    shift
    "$py" tools/benchmark.py --device cuda --objects "$n" --out "$out/benchmark_cuda_$n.json" "$@" 2>&1 \
        | tee "$out/benchmark_cuda_$n.txt"
    return "${PIPESTATUS[0]}"
}

bench_pair() {  # the 9,087-object class: loading on one thread and on canvas_threads; the GPU meshing (default)
    local n=9087  # and the writers' meshing, one after the other
    "$py" tools/benchmark.py --objects $n --load-only --repeat 3 --out "$out/loading_$n.json" 2>&1 \
        | tee "$out/loading_$n.txt" || return 1
    "$py" tools/benchmark.py --device cuda --objects $n --skip-carve --out "$out/benchmark_cuda_${n}.json" 2>&1 \
        | tee "$out/benchmark_cuda_${n}.txt" || return 1
    "$py" tools/benchmark.py --device cuda --objects $n --skip-carve --set mesher=skimage \
        --out "$out/benchmark_cuda_${n}_skimage.json" 2>&1 | tee "$out/benchmark_cuda_${n}_skimage.txt" || return 1
    "$py" - "$out" <<'PY' | tee -a "$out/ratios.txt"
import json, sys
d = sys.argv[1]
new, old = (json.load(open(f"{d}/benchmark_cuda_9087{s}.json"))["end_to_end"] for s in ("", "_skimage"))
print(f"9087 objects: mesher=auto {new['total_seconds']:.1f} s, mesher=skimage {old['total_seconds']:.1f} s, "
      f"new / old {new['total_seconds'] / old['total_seconds']:.3f}")
PY
}

many() {  # 12 classes of about 50 objects: viewpoints on the GPU (default) and on the CPU (alt), interleaved
    "$py" tools/benchmark.py --device cuda --many-classes --compare-set viewpoints.device=cpu \
        --out "$out/many_classes_cuda.json" 2>&1 | tee "$out/many_classes_cuda.txt"
    local rc=${PIPESTATUS[0]}
    grep "^new / " "$out/many_classes_cuda.txt" | sed 's/^/many classes: /' >> "$out/ratios.txt"
    return "$rc"
}

status=0
case "$step" in
    tests) run_tests || status=$? ;;
    bench1000) bench 1000 || status=$? ;;
    bench9087) bench_pair || status=$? ;;
    manyclasses) many || status=$? ;;
    all)
        run_tests || status=$?
        bench 1000 || status=$?
        bench_pair || status=$?
        many || status=$?
        ;;
esac
[ -f "$out/ratios.txt" ] && cat "$out/ratios.txt"
echo "results in $out"
exit "$status"
