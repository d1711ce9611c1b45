#!/usr/bin/env bash
# One short check of jaxiso on a GPU machine that has jax[cuda] installed and no network:
# the device and jax, an install that leaves jax alone, the test suite without the heavy
# cases, and the quick configuration of each scene kind's benchmark (implicit, volume,
# tetra). Every stage runs under `timeout` and reports its wall time; a failing stage is
# recorded and the next one runs. Results go to "${OUT:-gpu_results}":
#   failed_tests.txt  the tests that failed (or errored), named as they finished
#   summary.json      each stage's command, exit status, wall seconds, timeout, log tail;
#                     versions; the optional test tools found or missing
#   stages.log        every stage's full output, one after the other
#   implicit_<backend>.json, volume_<backend>.json, tetra_<backend>.json
#                     the benchmarks' own result files (charts are left out)
# At most 8 files, no deeper than $OUT itself (what the device runner brings back).
#
#   bash benchmarks/gpu_check.sh
#
# Environment (all optional):
#   OUT                  result folder (default gpu_results)
#   PYTHON               interpreter (default python3, else python)
#   GPU_CHECK_TESTS      test paths / node ids (default: the whole tests/ folder)
#   GPU_CHECK_WORKERS    pytest-xdist workers (default: half the cores, at most 12; 0: no xdist)
#   GPU_CHECK_INSTALL    1: pip install --no-index --no-deps --no-build-isolation -e .
#                        (jax and the rest stay as they are); 0: skip. Default: 1 where
#                        nvidia-smi is found, else 0 (on a shared CPU box the script must
#                        not install into someone's environment). The tree is imported
#                        through PYTHONPATH either way.
#   GPU_CHECK_BENCHES    which quick benchmarks to run (default "implicit volume tetra")
#   GPU_CHECK_BUDGET_S   wall seconds for the whole script (default 450, under 8 minutes);
#                        a stage's timeout is cut to what is left of it
#   GPU_CHECK_T_<STAGE>  a stage's own timeout in seconds (STAGE: ENV, INSTALL, TESTS,
#                        IMPLICIT, VOLUME, TETRA, DISTRIBUTED)
#
#   GPU_CHECK_DISTRIBUTED 0: skip the multi-process stage (default 1)
#   GPU_CHECK_STRICT     1: exit 1 when a stage failed (default 0: always exit 0 once the
#                        summary is written; summary.json's "ok" says whether all passed)

set -u

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$REPO" || exit 2
OUT_DIR="${OUT:-gpu_results}"
mkdir -p "$OUT_DIR" || exit 2
OUT_DIR="$(cd "$OUT_DIR" && pwd)"
WORK="$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")"
STAGES="$WORK/stages.tsv"  # name, rc, wall_s, timeout_s, log file, command
: >"$STAGES"
LOG="$OUT_DIR/stages.log"
: >"$LOG"

if [ -z "${PYTHON:-}" ]; then
    if command -v python3 >/dev/null 2>&1; then PYTHON=python3; else PYTHON=python; fi
fi
BUDGET_S="${GPU_CHECK_BUDGET_S:-450}"
# one worker per two cores, at most 12 (the GPU is shared by the workers)
NPROC=$(nproc 2>/dev/null || echo 8)
WORKERS="${GPU_CHECK_WORKERS:-$(( NPROC / 2 > 12 ? 12 : (NPROC / 2 < 1 ? 1 : NPROC / 2) ))}"
BENCHES="${GPU_CHECK_BENCHES:-implicit volume tetra}"
T_START=$(date +%s)

# the working tree is what runs, installed or not; output unbuffered; one process per
# pytest worker shares the GPU, so no process may take most of its memory up front
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}"
export PYTHONUNBUFFERED=1
export XLA_PYTHON_CLIENT_PREALLOCATE=false

now() { date +%s.%N; }

left_s() {  # whole seconds left of the budget
    echo $(( BUDGET_S - ($(date +%s) - T_START) ))
}

# stage NAME DEFAULT_TIMEOUT_S COMMAND...: runs COMMAND under timeout (cut to the budget
# left), appends its output to stages.log and records its exit status and wall time.
# Exit status 124/137: it ran past its timeout. A stage with no budget left is skipped
# (status "skipped").
stage() {
    local name="$1" default_t="$2"
    shift 2
    local var="GPU_CHECK_T_$(echo "$name" | tr '[:lower:]' '[:upper:]')"
    local t="${!var:-$default_t}"
    local left
    left=$(left_s)
    if [ "$left" -lt "$t" ]; then t=$left; fi
    local log="$WORK/$name.log"
    {
        echo
        echo "==================== stage $name (timeout ${t} s) ===================="
        echo "\$ ${*@Q}"
    } | tee -a "$LOG"
    if [ "$t" -lt 5 ]; then
        echo "stage $name skipped: ${left} s left of the ${BUDGET_S} s budget" | tee -a "$LOG"
        printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$name" "skipped" "0" "$t" "$log" "${*@Q}" \
            >>"$STAGES"
        : >"$log"
        write_summary
        return 0
    fi
    local t0 t1 rc
    t0=$(now)
    timeout -k 10 "$t" "$@" >"$log" 2>&1
    rc=$?
    t1=$(now)
    cat "$log" >>"$LOG"
    tail -n 25 "$log"
    local wall
    wall=$(awk -v a="$t0" -v b="$t1" 'BEGIN { printf "%.1f", b - a }')
    echo "---- stage $name: exit $rc, ${wall} s wall (timeout ${t} s)" | tee -a "$LOG"
    printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$name" "$rc" "$wall" "$t" "$log" "${*@Q}" >>"$STAGES"
    write_summary
    return 0
}

# summary.json from the stages so far (rewritten after every stage: a run cut short keeps
# what it measured)
write_summary() {
    "$PYTHON" - "$STAGES" "$OUT_DIR/summary.json" "$WORK" "$T_START" "$BUDGET_S" <<'EOF' \
        || echo "summary.json not written ($PYTHON failed)" >&2
import json, pathlib, sys, time

stages_tsv, out, work, t_start, budget = sys.argv[1:]
stages = []
for line in pathlib.Path(stages_tsv).read_text().splitlines():
    name, rc, wall, timeout_s, log, cmd = line.split("\t", 5)
    text = pathlib.Path(log).read_text(errors="replace") if pathlib.Path(log).exists() else ""
    skipped = rc == "skipped"
    stages.append(dict(
        name=name, command=cmd, exit_status=None if skipped else int(rc),
        status=("skipped" if skipped else "passed" if rc == "0"
                else "timed out" if rc in ("124", "137") else "failed"),
        wall_s=float(wall), timeout_s=int(timeout_s), log_tail=text[-3000:]))
extra = {}
info = pathlib.Path(work) / "info.json"
if info.exists():
    extra = json.loads(info.read_text())
ran = [s for s in stages if s["status"] != "skipped"]
summary = dict(ok=bool(ran) and all(s["status"] == "passed" for s in ran),
               total_wall_s=round(time.time() - float(t_start), 1),
               budget_s=int(budget), stages=stages, **extra)
pathlib.Path(out).write_text(json.dumps(summary, indent=1))
EOF
}

echo "gpu_check: repo $REPO, results in $OUT_DIR, budget ${BUDGET_S} s, python $PYTHON" \
    | tee -a "$LOG"

# -- 1. the machine: GPU, python, jax and the devices it sees ---------------------------
env_info() {
    if command -v nvidia-smi >/dev/null 2>&1; then
        nvidia-smi || echo "nvidia-smi failed (exit $?)"
    else
        echo "nvidia-smi: not found (no NVIDIA driver tools on this machine)"
    fi
    "$PYTHON" - "$WORK/info.json" <<'EOF'
import importlib.util, json, os, platform, sys

info = dict(python=sys.version.split()[0], executable=sys.executable,
            platform=platform.platform(), cpu_count=os.cpu_count())
tools = ("pytest", "xdist", "hypothesis", "nbformat", "nbclient", "ipykernel", "meshio",
         "matplotlib", "skimage", "vtk", "open3d")
info["modules"] = {m: importlib.util.find_spec(m) is not None for m in tools}
try:
    import jax
    info.update(jax_version=jax.__version__, backend=jax.default_backend(),
                devices=[f"{d.platform}:{d.id} {d.device_kind}" for d in jax.devices()])
    import jaxlib
    info["jaxlib_version"] = jaxlib.__version__
except Exception as e:  # record it; the stages after will fail and say more
    info["jax_error"] = f"{type(e).__name__}: {e}"
print(json.dumps(info, indent=1))
json.dump(info, open(sys.argv[1], "w"))
EOF
}
export -f env_info
export PYTHON WORK
stage env 60 bash -c env_info

# -- 2. install: the package only, jax and the rest as they are (no network) ------------
if [ -z "${GPU_CHECK_INSTALL:-}" ]; then
    if command -v nvidia-smi >/dev/null 2>&1; then GPU_CHECK_INSTALL=1; else GPU_CHECK_INSTALL=0; fi
fi
if [ "$GPU_CHECK_INSTALL" = "1" ]; then
    stage install 60 "$PYTHON" -m pip install --no-index --no-deps --no-build-isolation \
        --disable-pip-version-check -q -e .
else
    echo "install skipped (GPU_CHECK_INSTALL=${GPU_CHECK_INSTALL}); jaxiso is imported from" \
        "$REPO through PYTHONPATH" | tee -a "$LOG"
fi
"$PYTHON" -c "import jaxiso, sys; print('jaxiso', jaxiso.__version__, 'from', jaxiso.__file__)" \
    2>&1 | tee -a "$LOG"

# -- 3. the test suite without the heavy cases -------------------------------------------
has() { "$PYTHON" -c "import importlib.util, sys; sys.exit(importlib.util.find_spec('$1') is None)"; }
IGNORE=()
for m in meshio nbformat nbclient ipykernel; do
    if ! has "$m"; then
        for f in $(grep -lw "$m" tests/test_*.py 2>/dev/null); do
            case " ${IGNORE[*]-} " in *" --ignore=$f "*) ;; *) IGNORE+=("--ignore=$f") ;; esac
        done
        echo "test tool $m missing: ignoring $(grep -lw "$m" tests/test_*.py | tr '\n' ' ')" \
            | tee -a "$LOG"
    fi
done
XDIST=()
if [ "$WORKERS" != "0" ]; then
    if has xdist; then
        XDIST=(-n "$WORKERS" --dist loadfile --max-worker-restart=0)
    else
        echo "pytest-xdist missing: tests run in one process" | tee -a "$LOG"
    fi
fi
if has pytest && has hypothesis; then
    # shellcheck disable=SC2086  # GPU_CHECK_TESTS is a list of paths
    # -v names each test as it finishes (with xdist too), so a stage that runs past its
    # timeout still says which tests failed; no -x, for the same reason
    stage tests 240 "$PYTHON" -m pytest -m "not heavy" -v -rf --tb=line -p no:cacheprovider \
        ${XDIST[@]+"${XDIST[@]}"} ${IGNORE[@]+"${IGNORE[@]}"} ${GPU_CHECK_TESTS:-tests}
    grep -E "(FAILED|ERROR) tests/" "$LOG" | sort -u >"$OUT_DIR/failed_tests.txt"
else
    echo "tests skipped: pytest or hypothesis (tests/conftest.py needs it) is missing" \
        | tee -a "$LOG"
    printf '%s\t%s\t%s\t%s\t%s\t%s\n' tests skipped 0 0 /dev/null \
        "pytest (missing pytest or hypothesis)" >>"$STAGES"
    write_summary
fi

# -- 4. the quick configuration of each scene kind's benchmark ---------------------------
for kind in $BENCHES; do
    case "$kind" in
        implicit) t=60 ;;
        volume) t=100 ;;
        tetra) t=70 ;;
        *) echo "unknown benchmark $kind (implicit, volume, tetra)" | tee -a "$LOG"; continue ;;
    esac
    mkdir -p "$WORK/bench_$kind"
    stage "$kind" "$t" "$PYTHON" "benchmarks/bench_$kind.py" --quick --out "$WORK/bench_$kind"
    # the result file is rewritten after every section: a timed-out run keeps its sections
    for f in "$WORK/bench_$kind"/*.json; do
        [ -e "$f" ] && cp "$f" "$OUT_DIR/"
    done
done

# -- 5. more than one process (issue 30): `jaxiso render` on 1 process, then on one process
# per GPU (CUDA_VISIBLE_DEVICES=k, joined on 127.0.0.1), rays split and a volume in bricks;
# each process prints its render time (first call, incl. compile) to stages.log; with 4 or
# more GPUs, a 2 x 2 brick grid and 2 x 2 tet parts in one process (RESULT lines).
# GPU_CHECK_DISTRIBUTED=0 skips it; at most 8 processes.
distributed_check() {
    local ngpu port k args pids rc=0
    ngpu=$(nvidia-smi -L 2>/dev/null | wc -l)
    [ "$ngpu" -ge 1 ] || { echo "no GPU: distributed stage has nothing to run"; return 0; }
    [ "$ngpu" -le 8 ] || ngpu=8
    for extra in "" "--bricks"; do
        args=(-m jaxiso.cli render --scene volume:marschner_lobb:256 --size 1024 --out "")
        echo "== 1 process $extra"
        "$PYTHON" "${args[@]}" $extra || return 1
        [ "$ngpu" -ge 2 ] || continue
        echo "== $ngpu processes $extra"
        port=$((20000 + RANDOM % 20000))
        pids=()
        for k in $(seq 0 $((ngpu - 1))); do
            CUDA_VISIBLE_DEVICES=$k "$PYTHON" "${args[@]}" $extra --coordinator \
                "127.0.0.1:$port" --num-processes "$ngpu" --process-id "$k" --heartbeat 30 &
            pids+=($!)
        done
        for k in "${pids[@]}"; do wait "$k" || rc=1; done
    done
    # a brick grid (2, 2, 1) and a tet mesh in 2 x 2 parts over 4 GPUs of one process,
    # against the whole scenes (bytes per device, frame, hit agreement, depth difference)
    if [ "$ngpu" -ge 4 ]; then
        echo "== brick grid 2,2,1 over 4 GPUs (one process)"
        "$PYTHON" -c "import numpy as np; from jaxiso.volume import data; \
np.save('$WORK/ml256.npy', data.marschner_lobb(256))" || return 1
        CUDA_VISIBLE_DEVICES=0,1,2,3 "$PYTHON" benchmarks/bench_distributed.py --worker \
            --grid 2,2,1 --grid-size 1024 --tets 24 --repeats 3 \
            --volume-file "$WORK/ml256.npy" || rc=1
    fi
    return $rc
}
export -f distributed_check
if [ "${GPU_CHECK_DISTRIBUTED:-1}" = "1" ]; then
    stage distributed 300 bash -c distributed_check
fi

write_summary
END=$(date +%s)
echo
echo "gpu_check done in $((END - T_START)) s; summary:" | tee -a "$LOG"
"$PYTHON" - "$OUT_DIR/summary.json" <<'EOF' | tee -a "$LOG"
import json, sys

s = json.load(open(sys.argv[1]))
for st in s["stages"]:
    print(f"  {st['name']:<9} {st['status']:<9} exit {st['exit_status']}  "
          f"{st['wall_s']:7.1f} s (timeout {st['timeout_s']} s)")
print(f"  ok: {s['ok']}, {s['total_wall_s']} s of {s['budget_s']} s")
EOF
ls -l "$OUT_DIR"
rm -rf "$WORK"
if [ "${GPU_CHECK_STRICT:-0}" = "1" ]; then
    "$PYTHON" -c "import json, sys; sys.exit(0 if json.load(open(sys.argv[1]))['ok'] else 1)" \
        "$OUT_DIR/summary.json"
fi
