#!/usr/bin/env bash
# Every GPU check in one command that fits a lent machine's 8 minutes: the CUDA tests and the GPU benchmarks
# (docs/benchmarks.md), each new path timed against the current one in the same run (ratios in
# OUTDIR/ratios.txt). Run from the repository root:
#
#     bash tools/gpu_session.sh [all|lease|tests|e2e9087|many4|cad5|mesher2000|loading2000|bench1000|bench9087|manyclasses|cad8] [OUTDIR]
#     bash tools/gpu_session.sh --plan     # the plan of all and lease (steps, limits, their sum, the data); runs nothing
#     bash tools/gpu_session.sh --pack     # here, before a lease: what the lent machine lacks, into .whl/ and
#                                          # .gpu_shared/ (git-ignored), and the `run` call that carries them
#
# OUTDIR defaults to $OUT (the lent machine's result folder) or outputs/gpu; each step writes its log and JSON
# there. Python is $PYTHON or python3, with torch and CUDA. The packages of pyproject.toml (its dependencies and
# test extra) that the machine lacks travel as wheels in .whl/ (installed once into /tmp/carvi_site, never into
# the system): those an H100 image with torch 2.11 lacked, about 21 MB of cp312 manylinux wheels (the script's
# IMAGE_HAS, NOT_CARRIED and ALSO_CARRIED; the tests that need pycolmap skip without it).
#
#   all          the plan below: each step under `timeout` at its limit, the limits adding up to at most the
#                budget; each step's output on the terminal and in OUTDIR/<step>.log; status 1 when a step failed
#   lease        the same plan, the output in OUTDIR/<step>.log only, OUTDIR's small files packed into PACK
#                (default OUTDIR.tgz) after each step, so what finished comes back when a later one runs out
#                of time (a lent machine returns few files); status 0
#   STEPS="name:seconds ..." replaces the plan of all and lease (any step; steps outside the plan need seconds).
#
# On a lent machine, one command (its $OUT returns few files: the pack is one):
#     PACK=$OUT/results.tgz bash tools/gpu_session.sh lease /tmp/gpu
#
# A step of the plan runs alone under its own limit too. Inside it each run gets a share (`timeout`): a run
# stopped at its share leaves the other's time and still gives a bound on the ratio ("new / old < x").
#
# In the plan, loading2000: 2,000 objects loaded; the canvases' resampling by the batched op against the
# per-object reference (the 2 CPU cores: 0.467x at 9,087 objects). many4: 4 small classes, viewpoint_processes=4
# (their viewpoints at once, in CPU processes) against the default (auto: one after the other on the CPU);
# MANY4_VARIANTS="procs vprun" adds viewpoints.device=run (on CUDA, the default before auto).
#
# Steps outside the plan (no limit when run alone; H200 times: 16 slow cores, torch 2.11.0+cu130):
#   mesher2000   2,000 objects end to end, mesher=auto against mesher=skimage (H100: 1.163x, the writers kept up)
#   bench1000    tools/benchmark.py --device cuda --objects 1000, the carving comparison included
#   bench9087    the 9,087-object class: its loading (--load-only, as loading2000), then
#                mesher=auto and mesher=skimage end to end (H200: 54 s for auto, skimage stopped at 85 s)
#   manyclasses  the 12 many-class classes: viewpoint_processes=12 (their viewpoints at once, in CPU
#                processes), viewpoints.device=run (on CUDA: did not finish in 110 s on the H200), then the
#                default (auto: their viewpoints on the CPU), each variant at most MANY_ALL_S s with STEP_SECONDS
#                (MANY_VARIANTS="procs vprun" by default)
#   cad8         the 8-view CAD renders' cameras of the 12 classes, on the CPU then on CUDA, compared object by
#                object (tools/viewpoints_cad.py --compare; median <= 0.5 degrees per class). DEVICES=cuda runs
#                the CUDA side alone against a CPU run already in OUTDIR/cad8, DEVICES= only compares (cad5
#                too); H200: the CPU 80 s, CUDA over 120 s
#
# Data (carry them: generating them takes minutes; --plan says which are here):
#   outputs/bench/data/car1000_s0/{annotations,gt}.json      e2e9087, mesher2000, loading2000, bench* (larger
#                                                             classes are tiled from it)
#   outputs/bench/data/cad_v8_s0/annotations.json            many4, manyclasses
#   outputs/viewpoints_cad/renders_v8_s2/{annotations,gt}.json   cad5, cad8 (RENDERS=dir elsewhere; else
#                                                             rendered from ../shared/data/pascal3d_cad, CAD=path)
set -uo pipefail

# ---- the plan: what `all` and `lease` run, set from the H200's times (docs/benchmarks.md) ----------------------
BUDGET=470          # seconds the plan's limits may add up to: the 8 minutes, less 10 s of setup and packing
PLAN="tests:130 e2e9087:80 loading2000:20 many4:80 cad5:150"
MESHER_AUTO_S=45    # mesher2000: the mesher=auto run's share; mesher=skimage gets the rest
MANY_RUN_S=${MANY_RUN_S:-35}  # many4: each variant's share (vprun: stopped there on the H100); the default the rest
MANY_ALL_S=${MANY_ALL_S:-45}  # manyclasses: each variant's share; the default run gets the rest
CAD_RENDER_S=30     # cad5: rendering, when the renders were not carried
CAD_COMPARE_S=10    # cad5: the comparison (its interpreter imports torch)
RATIO_S=3           # kept at a step's end to write its ratios
MANY4_CLASSES=boat,bottle,bus,chair
CAD5_CLASSES=${CAD_CLASSES:-sofa,diningtable}  # CAD_CLASSES=...: others (sofa: the class no CUDA run reached yet;
                                               # diningtable: the one whose silhouette-only views parted)
# cad5's CUDA side: one process per group, all at once (a CUDA run keeps one CPU thread busy launching small
# kernels): on the H100 diningtable took 70 s there, sofa over 67 s; with CAD_CLASSES, one process
CAD5_CUDA_GROUPS=${CAD_CLASSES:-sofa diningtable}
STEPS_KNOWN="tests e2e9087 many4 cad5 mesher2000 loading2000 bench1000 bench9087 manyclasses cad8"

describe() {  # STEP: one line on what it runs
    case "$1" in
        tests) echo "pytest -m cuda (89-117 s on the H200, 108 s on the H100)" ;;
        e2e9087) echo "the 9,087-object class end to end with the defaults, once (the 10 s target; 60.5 s with the" \
                      "interpreter's start on the H100 at ba4e251: its canvases on 16 threads, its quality signals" \
                      "object by object)" ;;
        mesher2000) echo "(outside the plan since the H100's run) 2,000 objects end to end: mesher=auto (marching cubes batched on the GPU; at most" \
                         "${MESHER_AUTO_S} s) against mesher=skimage (the writers mesh; the rest); the batched op" \
                         "against scikit-image on 100 of the run's grids (H200, 9,087 objects: 54 s for auto," \
                         "skimage unfinished at 85 s)" ;;
        loading2000) echo "the 2,000-object class loaded, best of 2; the resampling of its canvases by the batched" \
                          "op against the per-object reference" ;;
        many4) echo "the many-class benchmark on ${MANY4_CLASSES//,/, } (4 of 12): ${MANY4_VARIANTS:-procs}" \
                    "(procs: viewpoint_processes=4, their viewpoints at once in CPU processes; vprun:" \
                    "viewpoints.device=run, unfinished at 47 s on the H100; each at most ${MANY_RUN_S} s)" \
                    "against the default, auto (these small classes' viewpoints on the CPU, one after the other)" ;;
        cad5) echo "the 8-view CAD cameras of ${CAD5_CLASSES//,/, } (sofa: no CUDA run reached it yet), compared" \
                   "object by object (median <= 0.5 degrees per class): the CPU side (4 torch threads) beside the" \
                   "CUDA side (viewpoints.device=run), in processes of ${CAD5_CUDA_GROUPS// / and } at the same" \
                   "time; a class a side did not reach is listed" ;;
        bench1000|bench9087|manyclasses|cad8) echo "(outside the plan: see --help)" ;;
        *) echo "UNKNOWN STEP" ;;
    esac
}

plan_entries() {  # the plan's "step seconds", one a line (STEPS replaces it; a step of PLAN may leave out its
                 # seconds; a missing limit is "?")
    local s limit
    for s in ${STEPS:-$PLAN}; do
        limit=${s#*:}
        [ "$limit" = "$s" ] && limit=$(plan_limit "$s")
        echo "${s%%:*} ${limit:-?}"
    done
}

plan_limit() {  # STEP: its seconds in PLAN (empty when it is not in it)
    local s
    for s in $PLAN; do [ "${s%%:*}" = "$1" ] && { echo "${s#*:}"; return; }; done
}

print_plan() {  # prints the plan; status 1 when a step is unknown, a limit not a positive integer or the sum over budget
    local name limit sum=0 bad=0
    echo "plan: each step under \`timeout\` at its limit (seconds); budget $BUDGET s"
    while read -r name limit; do
        case " $STEPS_KNOWN " in *" $name "*) ;; *) bad=1 ;; esac
        case "$limit" in ''|*[!0-9]*|0) bad=1; limit="?" ;; *) sum=$(( sum + limit )) ;; esac
        describe "$name" | fold -s -w 88 | { read -r first; printf '  %-12s %4s s  %s\n' "$name" "$limit" "$first"
                                             sed 's/^/                       /'; }
    done < <(plan_entries)
    printf '  %-12s %4s s  (budget %s s)\n' "sum" "$sum" "$BUDGET"
    [ "$sum" -gt "$BUDGET" ] && { echo "the plan is OVER its budget"; bad=1; }
    [ "$bad" = 1 ] && echo "the plan is not valid: unknown step, missing limit or over budget"
    echo "data:"
    data_line outputs/bench/data/car1000_s0/annotations.json "e2e9087 (else generated: minutes, past its limit)"
    data_line outputs/bench/data/cad_v8_s0/annotations.json "many4 (else rendered or generated: past its limit)"
    data_line "${RENDERS:-outputs/viewpoints_cad/renders_v8_s2}/annotations.json" "cad5 (else rendered, at most $CAD_RENDER_S s)"
    data_line ../shared/data "tests (the tests on real data skip without it)"
    return "$bad"
}

# ---- packages: pyproject.toml's dependencies and test extra, the one list of them ------------------------------
# The lent machine imports them all (NOT_CARRIED left out), or else installs the wheels of .whl/. --pack downloads
# (cp312 manylinux wheels, without their dependencies) those IMAGE_HAS leaves, and ALSO_CARRIED; PACK_WHEELS="..."
# replaces that list (empty: no wheels).
IMAGE_HAS="torch numpy scipy scikit-image tqdm matplotlib PyYAML Pillow pytest"  # an H100 image with torch 2.11
NOT_CARRIED="pycolmap ray ruff pytest-xdist"  # the tests that need them skip without them
ALSO_CARRIED="kornia_rs numcodecs donfig google-crc32c"  # kornia's and zarr's dependencies the image lacked
PYPROJECT="$(dirname "$0")/../pyproject.toml"
PACK_PYTHON=${PACK_PYTHON:-3.12}  # the lent machine's Python
# argv: MODE PYPROJECT IMAGE_HAS NOT_CARRIED ALSO_CARRIED. wheels: the requirements --pack downloads, one a line;
# check: imports the modules of the requirements, status 1 when one fails. Python 3.11 or later (tomllib).
PACKAGES_PY='import importlib, re, sys, tomllib
mode, path, image, skip, also = sys.argv[1:6]
key = lambda r: re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9._-]+", r).group()).lower()
image, skip = ({key(n) for n in names.split()} for names in (image, skip))
with open(path, "rb") as f:
    project = tomllib.load(f)["project"]
reqs = [r for r in project["dependencies"] + project["optional-dependencies"]["test"] if key(r) not in skip]
if mode == "wheels":
    print(*[r for r in reqs if key(r) not in image], *also.split(), sep="\n")
    sys.exit(0)
modules = {"scikit-image": "skimage", "pyyaml": "yaml", "pillow": "PIL"}
failed = []
for r in reqs:
    try:
        importlib.import_module(modules.get(key(r), key(r).replace("-", "_")))
    except Exception:
        failed.append(r)
sys.exit(f"not importable: {failed}" if failed else 0)'

packages() {  # PYTHON MODE: PACKAGES_PY's MODE (wheels, check) on PYPROJECT
    "$1" -c "$PACKAGES_PY" "$2" "$PYPROJECT" "$IMAGE_HAS" "$NOT_CARRIED" "$ALSO_CARRIED"
}

pack_for_lease() {  # .whl/ (PACK_WHEELS, else `packages wheels`; none when empty) and .gpu_shared/ (../shared/data,
                    # the steps' inputs)
    local f
    if [ -z "${PACK_WHEELS+set}" ]; then
        PACK_WHEELS=$(packages "${PYTHON:-python3}" wheels) || return 1
    fi
    if [ -n "$PACK_WHEELS" ]; then
        echo "wheels: ${PACK_WHEELS//$'\n'/ }"
        rm -rf .whl  # an earlier pack's versions beside newer ones would make the lease's install fail
        # shellcheck disable=SC2086  # the list splits into packages
        "${PYTHON:-python3}" -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
            --implementation cp --python-version "$PACK_PYTHON" --platform manylinux2014_x86_64 \
            --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 -d .whl $PACK_WHEELS || return 1
    fi
    rm -rf .gpu_shared && mkdir -p .gpu_shared/outputs || return 1
    [ -d ../shared/data ] && cp -r ../shared/data .gpu_shared/data
    for f in outputs/bench/data/car1000_s0/{annotations,gt}.json outputs/bench/data/cad_v8_s0/annotations.json \
             outputs/viewpoints_cad/renders_v8_s2/{annotations,gt}.json; do
        [ -e "$f" ] && mkdir -p ".gpu_shared/$(dirname "$f")" && cp "$f" ".gpu_shared/$f"
    done
    echo "packed: $(find .whl -type f -name '*.whl' 2>/dev/null | wc -l) wheels in .whl/, $(du -sh .gpu_shared | cut -f1) in .gpu_shared/"
    echo "then: run(carry=[\".whl\", \".gpu_shared\"], timeout_s=595, command=\"set -o pipefail; mkdir -p ../shared &&" \
         "{ [ ! -d .gpu_shared/data ] || cp -r .gpu_shared/data ../shared/; } && cp -r .gpu_shared/outputs . &&" \
         "export CARVI_TORCH_CACHE=/tmp/ct_cache PYTHONUNBUFFERED=1 && PACK=\$OUT/results.tgz bash tools/gpu_session.sh" \
         "lease /tmp/gpu > \$OUT/lease.log 2>&1; cat /tmp/gpu/steps.txt /tmp/gpu/ratios.txt\")"
}

data_line() {  # PATH WHAT
    if [ -e "$1" ]; then printf '  here    %s\n' "$1"; else printf '  absent  %s: %s\n' "$1" "$2"; fi
}

if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then  # the comment above, then the plan
    sed -n '2,/^set /p' "$0" | sed -e '$d' -e 's/^# \{0,1\}//'
    echo
    print_plan
    exit 0
fi
if [ "${1:-}" = "--plan" ]; then
    print_plan
    exit $?
fi
if [ "${1:-}" = "--pack" ]; then
    pack_for_lease
    exit $?
fi
step=${1:-all}
out=${2:-${OUT:-outputs/gpu}}
py=${PYTHON:-python3}
case " all lease $STEPS_KNOWN " in
    *" $step "*) ;;
    *) echo "unknown step '$step' (all, lease, ${STEPS_KNOWN// /, })" >&2; exit 2 ;;
esac
mkdir -p "$out"

# ---- packages: installed once; the steps of all and lease inherit the path (CARVI_GPU_READY) ------------------
if [ -z "${CARVI_GPU_READY:-}" ]; then
    if ! packages "$py" check 2>/dev/null && [ -d .whl ] && compgen -G ".whl/*.whl" >/dev/null; then
        "$py" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target /tmp/carvi_site .whl/*.whl || exit 1
        export PYTHONPATH="/tmp/carvi_site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
    else
        export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
    fi
fi

# ---- how each step times its runs --------------------------------------------------------------------------
# A step of the plan ends at STEP_END (epoch seconds): the runner's, or its plan limit (STEP_SECONDS, if set) from
# its start when it runs alone. Every run inside gets at most its share and never goes past that end, so the step's own runs stop
# before the runner's `timeout` stops the step. Steps outside the plan run without limits.
part_limit() {  # SHARE RESERVE: the next run's seconds: at most SHARE (0: no share), RESERVE kept before the
                # step's end, and one more second for the clock's whole seconds (a run started late in a second
                # still ends by the step's end); "none" (no limit) for a step without an end (run alone, outside
                # the plan)
    [ -z "${STEP_END:-}" ] && { echo none; return; }
    local left=$(( STEP_END - $(date +%s) - $2 - 1 ))
    if [ "$1" -gt 0 ] && [ "$1" -lt "$left" ]; then echo "$1"; else echo "$left"; fi
}

timed() {  # NAME LIMIT CMD...: CMD under `timeout LIMIT` ("none": no limit; at most 0: not run), its output also in
           # OUTDIR/NAME.txt, "status wall_seconds limit" in OUTDIR/NAME.run; returns its status (124, 137: stopped)
    local name=$1 limit=$2 t0 rc
    shift 2
    if [ "$limit" != none ] && [ "$limit" -le 0 ]; then
        echo "$name: not run, no time left in the step" | tee "$out/$name.txt"
        echo "125 0 0" > "$out/$name.run"
        return 125
    fi
    echo "$name (limit $limit s): $*"
    t0=$(date +%s.%N)
    if [ "$limit" = none ]; then
        "$@" 2>&1 | tee "$out/$name.txt"
    else
        timeout -k 3 "$limit" "$@" 2>&1 | tee "$out/$name.txt"
    fi
    rc=${PIPESTATUS[0]}
    echo "$rc $(awk -v a="$t0" -v b="$(date +%s.%N)" 'BEGIN { printf "%.1f", b - a }') $limit" > "$out/$name.run"
    echo "$name: status $rc after $(cut -d' ' -f2 "$out/$name.run") s"
    return "$rc"
}

jval() {  # FILE DOTTED.KEY: one value of a JSON record (empty when the file or the key is absent)
    "$py" -c 'import json, sys
try:
    v = json.load(open(sys.argv[1]))
    for k in sys.argv[2].split("."):
        v = v[k]
    print(v)
except (OSError, ValueError, KeyError, TypeError):
    pass' "$1" "$2" 2>/dev/null
}

ratio() {  # LABEL NEW OLD NEW_SECONDS OLD_SECONDS: "LABEL: new / old" into ratios.txt, from the runs' seconds (their
           # JSON) when both finished, else a bound from their wall times and the limit of the one stopped
    local label=$1 new=$2 old=$3 nrc=missing nw nl orc=missing ow ol line
    [ -f "$out/$new.run" ] && read -r nrc nw nl < "$out/$new.run"
    [ -f "$out/$old.run" ] && read -r orc ow ol < "$out/$old.run"
    local both='BEGIN { printf "%s %.1f s, %s %.1f s: %s / %s %.3f", a, x, b, y, a, b, x / y }'
    local below='BEGIN { printf "%s %.1f s (whole tool), %s stopped at its %d s limit: %s / %s < %.3f", a, x, b, y, a, b, x / y }'
    local above='BEGIN { printf "%s stopped at its %d s limit, %s %.1f s (whole tool): %s / %s > %.3f", a, x, b, y, a, b, x / y }'
    if [ "$nrc" = 0 ] && [ "$orc" = 0 ] && awk -v x="$4" -v y="$5" 'BEGIN { exit !(x + 0 > 0 && y + 0 > 0) }'; then
        line=$(awk -v x="$4" -v y="$5" -v a="$new" -v b="$old" "$both")
    elif [ "$nrc" = 0 ] && { [ "$orc" = 124 ] || [ "$orc" = 137 ]; }; then
        line=$(awk -v x="$nw" -v y="$ol" -v a="$new" -v b="$old" "$below")
    elif { [ "$nrc" = 124 ] || [ "$nrc" = 137 ]; } && [ "$orc" = 0 ]; then
        line=$(awk -v x="$nl" -v y="$ow" -v a="$new" -v b="$old" "$above")
    else
        line="no ratio: $new status $nrc, $old status $orc; seconds in their records: '$4', '$5'"
    fi
    echo "$label: $line" | tee -a "$out/ratios.txt"
}

# ---- the 8-view CAD renders' cameras, CPU against CUDA (cad5, cad8) ---------------------------------------------
#     bash tools/gpu_session.sh cad8|cad5 [OUTDIR]
# Renders the PASCAL3D+ CAD models at 8 views per model (seed 2: the trains' template start), reconstructs their
# cameras on the CPU and on CUDA (tools/viewpoints_cad.py, default settings) and compares them object by object
# (tools/viewpoints_cad.py --compare: the angle between the final cameras, the SfM start each class kept, the
# shapes its mixture kept, each object's camera_choice, each side's seconds of SfM and refinement), into
# OUTDIR/<step>_agreement.json. Tolerance (docs/viewpoints.md): median angle <= 0.5 degrees per class. A class a
# run did not reach is listed as such. cad8: every class, the CPU side then the CUDA side. cad5: five classes, the
# CPU side (4 torch threads) and the CUDA side's processes (each main process keeps one thread) at the same time.
cad_dir() {  # WORK OVERRIDE...: the folder of a run of tools/viewpoints_cad.py --views 8 --seed 2 (its recon_dir)
    local d="$1/cameras" o
    shift
    for o in "$@"; do d+="_${o//[^[:alnum:]]/-}"; done
    echo "${d}_v8_renders-s2"
}

cad() {  # STEP CPU_CLASSES CUDA_GROUPS BESIDE: the CPU side on CPU_CLASSES (comma-separated; empty: all), the CUDA
         # side in one process per group of CUDA_GROUPS (space-separated; empty: one, with CPU_CLASSES); BESIDE=1:
         # every process at the same time, else the CPU side then the CUDA side
    local name=$1 work="$out/$1" cad=${CAD:-../shared/data/pascal3d_cad} renders dev limit pid status=0 k
    local groups=() cpu_ovr=() cuda_dirs=() g cmd
    [ -n "$2" ] && cpu_ovr=("classes=[$2]")
    read -r -a groups <<< "$3"
    [ "${#groups[@]}" = 0 ] && groups=("$2")
    renders=${RENDERS:-outputs/viewpoints_cad/renders_v8_s2}
    if [ -n "${DEVICES-cpu cuda}" ] && [ ! -f "$work/renders_v8_s2/annotations.json" ]; then
        if [ -f "$renders/annotations.json" ]; then  # carried
            mkdir -p "$work/renders_v8_s2" && cp "$renders/annotations.json" "$renders/gt.json" "$work/renders_v8_s2/"
        else
            timed "${name}_render" "$(part_limit "$CAD_RENDER_S" 0)" "$py" tools/viewpoints_cad.py --views 8 --seed 2 \
                --quiet --cad "$cad" --work "$work" --render-only || status=1
        fi
    fi
    local base=("$py" tools/viewpoints_cad.py --views 8 --seed 2 --quiet --cad "$cad" --work "$work") pids=()
    for g in "${groups[@]}"; do
        if [ -n "$g" ]; then cuda_dirs+=("$(cad_dir "$work" device=cuda viewpoints.device=run "classes=[$g]")")
        else cuda_dirs+=("$(cad_dir "$work" device=cuda viewpoints.device=run)"); fi
    done
    for dev in ${DEVICES-cpu cuda}; do
        limit=$(part_limit 0 "$CAD_COMPARE_S")
        if [ "$dev" = cpu ]; then
            cmd=("${base[@]}" --out "$out/${name}_cpu.json" device=cpu ${cpu_ovr[@]+"${cpu_ovr[@]}"})
            if [ "$4" = 1 ]; then
                timed "${name}_cpu" "$limit" env CARVI_THREADS=4 "${cmd[@]}" > /dev/null &
                pids+=($!)
            else
                timed "${name}_cpu" "$limit" "${cmd[@]}" || status=1
            fi
            continue
        fi
        k=0
        for g in "${groups[@]}"; do
            k=$(( k + 1 ))
            local tag="${name}_$dev" ovr=("device=$dev" viewpoints.device=run)  # not auto: the CPU for these classes
            [ "${#groups[@]}" -gt 1 ] && tag+="$k"
            [ -n "$g" ] && ovr+=("classes=[$g]")
            cmd=("${base[@]}" --out "$out/$tag.json" "${ovr[@]}")
            if [ "$4" = 1 ]; then
                timed "$tag" "$limit" "${cmd[@]}" > /dev/null &
                pids+=($!)
            else
                timed "$tag" "$limit" "${cmd[@]}" || status=1
            fi
        done
    done
    for pid in ${pids[@]+"${pids[@]}"}; do  # the runs that ran beside one another
        wait "$pid" || status=1
    done
    timed "${name}_compare" "$(part_limit 0 0)" "$py" tools/viewpoints_cad.py --compare \
        "$(cad_dir "$work" device=cpu ${cpu_ovr[@]+"${cpu_ovr[@]}"})" "${cuda_dirs[@]}" \
        --out "$out/${name}_agreement.json" || status=1
    local c g2
    c=$(jval "$out/${name}_agreement.json" viewpoint_seconds.cpu)
    g2=$(jval "$out/${name}_agreement.json" viewpoint_seconds.cuda)
    { grep -h "classes compared\|largest class median\|no class compared" "$out/${name}_compare.txt" \
          | sed "s/^/$name: /"
      if [ -n "$c" ] && [ -n "$g2" ]; then
          awk -v c="$c" -v g="$g2" -v n="$name" -v b="$4" -v p="${#groups[@]}" 'c > 0 && g > 0 {
              printf "%s: SfM + refinement of the classes compared, cuda %.1f s / cpu %.1f s: cuda / cpu %.3f%s\n",
              n, g, c, g / c, (b == 1 ? " (the CPU side and " p " CUDA process(es) at the same time)" : "") }' <<< ""
      fi; } | tee -a "$out/ratios.txt"
    return "$status"
}

case "$step" in
    cad8) cad cad8 "" "" 0; rc=$?; echo "results in $out"; exit "$rc" ;;
    cad5)
        [ -z "${STEP_END:-}" ] && STEP_END=$(( $(date +%s) + ${STEP_SECONDS:-$(plan_limit cad5)} ))
        cad cad5 "$CAD5_CLASSES" "$CAD5_CUDA_GROUPS" 1; rc=$?; echo "results in $out"; exit "$rc" ;;
esac

# ---- the device, once (the steps of all and lease inherit the check) ------------------------------------------
if [ -z "${CARVI_GPU_READY:-}" ]; then
    if ! "$py" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
        echo "no CUDA device visible to $py: nothing to do here" >&2
        exit 2
    fi
    { nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>/dev/null
      "$py" -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"; } | tee "$out/device.txt"
fi

# ---- all, lease: every step of the plan under its own limit ----------------------------------------------------
#     STEPS="tests:170 cad5:200" PACK=$OUT/results.tgz bash tools/gpu_session.sh lease /tmp/gpu
# Each step runs under `timeout` (the seconds after the colon); its start, end and status go to OUTDIR/steps.txt.
# lease packs OUTDIR (without meshes, voxels or arrays) into PACK (default OUTDIR.tgz) after each step.
run_plan() {  # PACK (empty: no packing)
    local t0 name limit rc failed=0
    print_plan | tee "$out/plan.txt"
    export CARVI_GPU_READY=1
    t0=$(date +%s)
    while read -r name limit <&3; do  # fd 3: the steps' commands keep the caller's standard input
        if [ "$limit" = "?" ]; then
            echo "[$(( $(date +%s) - t0 )) s] $name not run: no limit given" | tee -a "$out/steps.txt"
            failed=1
            continue
        fi
        echo "[$(( $(date +%s) - t0 )) s] start $name (limit $limit s)" | tee -a "$out/steps.txt"
        if [ -n "$1" ]; then
            STEP_END=$(( $(date +%s) + limit - 2 )) timeout -k 5 "$limit" bash "$0" "$name" "$out" > "$out/$name.log" 2>&1
            rc=$?
        else
            STEP_END=$(( $(date +%s) + limit - 2 )) timeout -k 5 "$limit" bash "$0" "$name" "$out" 2>&1 \
                | tee "$out/$name.log"
            rc=${PIPESTATUS[0]}
        fi
        [ "$rc" = 0 ] || failed=1
        echo "[$(( $(date +%s) - t0 )) s] end $name, status $rc" | tee -a "$out/steps.txt"
        if [ -n "$1" ]; then
            # GNU tar's status 1: a file changed while read (a run stopped late still writing); the pack is made
            tar czf "$1" -C "$out" --exclude=meshes --exclude='*.npz' --exclude='*.npy' --exclude='*.ply' \
                --exclude='*.obj' --exclude='*.zarr' --exclude=renders_v8_s2 . || [ $? -le 1 ] || exit 1
        fi
    done 3< <(plan_entries)
    echo "ratios (new / current, measured in this run):"
    cat "$out/ratios.txt" 2>/dev/null
    return "$failed"
}

if [ "$step" = "lease" ]; then
    run_plan "${PACK:-${out%/}.tgz}"
    exit 0
fi
if [ "$step" = "all" ]; then
    run_plan ""
    exit $?
fi

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

bench_pair() {  # the 9,087-object class: loading and its resampling (as loading2000); the GPU meshing (default)
    local n=9087  # and the writers' meshing, one after the other
    "$py" tools/benchmark.py --objects $n --load-only --repeat 3 --out "$out/loading_$n.json" 2>&1 \
        | tee "$out/loading_$n.txt" || return 1
    mesher_pair "$n" 0 200
}

mesher_pair() {  # OBJECTS SHARE GRIDS: mesher=auto (at most SHARE s; 0: no share) against mesher=skimage, end to end;
                 # the auto run also times the batched op against scikit-image on GRIDS of its grids
    local n=$1 rc=0 common=(tools/benchmark.py --device cuda --objects "$1" --skip-carve)
    timed "mesher${n}_auto" "$(part_limit "$2" 0)" "$py" "${common[@]}" --mesh-objects "$3" --repeat 2 \
        --out "$out/mesher${n}_auto.json" || rc=1
    timed "mesher${n}_skimage" "$(part_limit 0 "$RATIO_S")" "$py" "${common[@]}" --mesh-objects 0 \
        --set mesher=skimage --out "$out/mesher${n}_skimage.json" || rc=1
    ratio "$n objects end to end, interpreter start included" "mesher${n}_auto" "mesher${n}_skimage" \
        "$(jval "$out/mesher${n}_auto.json" end_to_end.wall_seconds_with_startup)" \
        "$(jval "$out/mesher${n}_skimage.json" end_to_end.wall_seconds_with_startup)"
    local op
    op=$(jval "$out/mesher${n}_auto.json" meshing.torch_over_skimage)
    if [ -n "$op" ]; then
        awk -v r="$op" -v n="$n" -v g="$3" \
            'BEGIN { printf "%s objects, marching cubes of %s grids: batched torch op / scikit-image %.3f\n", n, g, r }' \
            | tee -a "$out/ratios.txt"
    fi
    return "$rc"
}

loading() {  # the 2,000-object class loaded; its canvases resampled by the batched op and the per-object reference
    timed loading2000 "$(part_limit 0 0)" "$py" tools/benchmark.py --device cuda --objects 2000 --load-only \
        --repeat 2 --out "$out/loading2000.json" || return 1
    local r one same
    r=$(jval "$out/loading2000.json" loading.resampling.batched_over_reference)
    one=$(jval "$out/loading2000.json" "loading.best_seconds.one thread")
    same=$(jval "$out/loading2000.json" loading.resampling.same_canvases)
    if [ -n "$r" ]; then
        awk -v r="$r" -v a="$one" -v s="$same" 'BEGIN { printf "loading 2000 objects: %.2f s; resampling: batched " \
            "op / per-object reference %.3f (the same canvases: %s)\n", a, r, s }' | tee -a "$out/ratios.txt"
    fi
}

many_pair() {  # NAME CLASSES (comma-separated; empty: all 12) SHARE VARIANTS: each variant's run (at most SHARE s
               # each), then the default (the rest; viewpoints.device=auto: the CPU for these small classes), whole
               # runs (tools/benchmark.py --many-classes, one round each). VARIANTS: vprun (viewpoints.device=run:
               # on CUDA, the default before auto; its ratio is default / vprun) and procs (viewpoint_processes = the
               # classes, at most 12: their viewpoints at once in CPU processes; procs / default)
    local name=$1 rc=0 sel=() args=(tools/benchmark.py --device cuda --many-classes) v n setting
    [ -n "$2" ] && sel=("classes=[$2]")
    n=$(( $(echo "${2:-a,b,c,d,e,f,g,h,i,j,k,l}" | tr ',' '\n' | wc -l) ))
    [ "$n" -gt 12 ] && n=12
    for v in $4; do
        case "$v" in
            procs) setting="viewpoint_processes=$n" ;;
            vprun) setting="viewpoints.device=run" ;;
            *) echo "$name: unknown variant '$v' (procs, vprun)" >&2; return 2 ;;
        esac
        timed "${name}_$v" "$(part_limit "$3" 0)" "$py" "${args[@]}" --set ${sel[@]+"${sel[@]}"} "$setting" \
            --out "$out/${name}_$v.json" || rc=1
    done
    timed "${name}_default" "$(part_limit 0 "$RATIO_S")" "$py" "${args[@]}" ${sel[@]+--set "${sel[@]}"} \
        --out "$out/${name}_default.json" || rc=1
    local key=many_classes.best.new.wall_seconds_with_startup
    for v in $4; do
        if [ "$v" = vprun ]; then
            ratio "$name, whole processes" "${name}_default" "${name}_$v" "$(jval "$out/${name}_default.json" $key)" \
                "$(jval "$out/${name}_$v.json" $key)"
        else
            ratio "$name, whole processes" "${name}_$v" "${name}_default" "$(jval "$out/${name}_$v.json" $key)" \
                "$(jval "$out/${name}_default.json" $key)"
        fi
    done
    return "$rc"
}

status=0
case "$step" in
    tests) run_tests || status=$? ;;
    bench1000) bench 1000 || status=$? ;;
    bench9087) bench_pair || status=$? ;;
    e2e9087)
        [ -z "${STEP_END:-}" ] && STEP_END=$(( $(date +%s) + ${STEP_SECONDS:-$(plan_limit e2e9087)} ))
        timed e2e9087 "$(part_limit 0 0)" "$py" tools/benchmark.py --device cuda --objects 9087 --skip-carve \
            --mesh-objects 0 --out "$out/e2e9087.json" || status=$? ;;
    manyclasses)
        [ -z "${STEP_END:-}" ] && [ -n "${STEP_SECONDS:-}" ] && STEP_END=$(( $(date +%s) + STEP_SECONDS ))
        many_pair manyclasses "" "$MANY_ALL_S" "${MANY_VARIANTS:-procs vprun}" || status=$? ;;
    mesher2000|loading2000|many4)
        [ -z "${STEP_END:-}" ] && STEP_END=$(( $(date +%s) + ${STEP_SECONDS:-$(plan_limit "$step")} ))
        case "$step" in
            mesher2000) mesher_pair 2000 "$MESHER_AUTO_S" 100 || status=$? ;;
            loading2000) loading || status=$? ;;
            many4) many_pair many4 "$MANY4_CLASSES" "$MANY_RUN_S" "${MANY4_VARIANTS:-procs}" || status=$? ;;
        esac ;;
esac
echo "results in $out"
exit "$status"
