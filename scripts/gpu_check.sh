#!/usr/bin/env bash
# The prepared GPU check: set up, run the test suite in cuda_ad_rgb, run the
# quick benchmark in cuda_ad_rgb, and leave every log and result in one folder.
#
#   bash scripts/gpu_check.sh [FOLDER]      # default: $OUT if set, else out/gpu_check
#
# Environment: GPU_CHECK_PARTS (default "suite bench": either or both), SUITE_TIMEOUT / BENCH_TIMEOUT
# (seconds, default 540 / 240), PYTEST_ARGS (extra pytest arguments, e.g. "-x" or a file list),
# FORCE_SETUP=1 (run scripts/setup.sh --test even where .venv already works).
# Writes FOLDER/summary.txt (one line per step), nvidia-smi.txt, setup.log, variant.txt, suite.log,
# suite.xml (JUnit), bench_quick.log and bench_quick/ (results.json, RESULTS.md).
# Exit status: 0 all passed; 1 a step failed; 2 this machine cannot run cuda_ad_rgb (no CUDA device
# or driver: said in one line, nothing else is run).
set -uo pipefail
cd "$(dirname "$0")/.."
out="${1:-${OUT:-out/gpu_check}}"
parts="${GPU_CHECK_PARTS:-suite bench}"
mkdir -p "$out"
: > "$out/summary.txt"
log() { echo "gpu_check: $*" | tee -a "$out/summary.txt"; }

log "started $(date -u +%FT%TZ) on $(hostname), commit $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
if command -v nvidia-smi > /dev/null 2>&1; then
    nvidia-smi > "$out/nvidia-smi.txt" 2>&1
    log "GPU: $(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null | head -1)"
else
    log "nvidia-smi not found"
fi

# Setup (skipped where the venv already imports mitsuba, unless FORCE_SETUP=1).
if [ "${FORCE_SETUP:-0}" = 1 ] || ! .venv/bin/python -c "import mfnormal, mitsuba" > /dev/null 2>&1; then
    if ! bash scripts/setup.sh --test > "$out/setup.log" 2>&1; then
        log "setup failed: $(tail -1 "$out/setup.log")"
        exit 1
    fi
    log "setup: $(tail -1 "$out/setup.log")"
else
    log "setup: skipped (.venv works; FORCE_SETUP=1 to run it)"
fi

# cuda_ad_rgb must load here: one line and exit 2 otherwise.
if ! .venv/bin/python - > "$out/variant.txt" 2>&1 <<'EOF'
import mfnormal  # noqa: F401
from mfnormal.cli import CLIError, setup_variant
try:
    mi = setup_variant("cuda_ad_rgb")
except CLIError as exc:
    raise SystemExit(f"error: {exc}")
import drjit as dr
x = dr.arange(mi.Float, 1024)
assert dr.slice(dr.sum(x)) == 523776.0
print(f"variant {mi.variant()}, Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}: a kernel ran")
EOF
then
    log "cuda_ad_rgb unavailable: $(tail -1 "$out/variant.txt")"
    exit 2
fi
log "$(tail -1 "$out/variant.txt")"

status=0
if [[ " $parts " == *" suite "* ]]; then
    start=$(date +%s)
    # shellcheck disable=SC2086  (PYTEST_ARGS is a list of words)
    MFNORMAL_VARIANT=cuda_ad_rgb timeout "${SUITE_TIMEOUT:-540}" .venv/bin/python -m pytest -q -rfEs \
        --junitxml="$out/suite.xml" ${PYTEST_ARGS:-} > "$out/suite.log" 2>&1
    rc=$?
    log "suite in cuda_ad_rgb: exit $rc after $(( $(date +%s) - start )) s: $(tail -1 "$out/suite.log")"
    [ "$rc" = 0 ] || status=1
fi
if [[ " $parts " == *" bench "* ]]; then
    start=$(date +%s)
    timeout "${BENCH_TIMEOUT:-240}" .venv/bin/python -m benchmarks.run --quick --variant cuda_ad_rgb \
        --out "$out/bench_quick" > "$out/bench_quick.log" 2>&1
    rc=$?
    log "benchmarks/run.py --quick --variant cuda_ad_rgb: exit $rc after $(( $(date +%s) - start )) s"
    grep -E "^  (PASS|FAIL|n/a)" "$out/bench_quick.log" >> "$out/summary.txt"
    [ "$rc" = 0 ] || status=1
fi
log "done $(date -u +%FT%TZ), exit $status"
exit $status
