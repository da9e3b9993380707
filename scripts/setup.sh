#!/usr/bin/env bash
# Set up mfnormal on a fresh machine: a libLLVM >= 17 for Dr.Jit, a virtual
# environment in .venv with the tested Mitsuba/Dr.Jit, and the package itself.
# With --test, also what the test suite needs (pytest, pytest-xdist, scipy, matplotlib,
# selenium, Sphinx and MyST for the documentation build, Dask.distributed for the
# --cluster tests, xatlas and fast-simplification for validation/real_assets.py,
# Debian's headless Chromium for the browser tests of the report and the documentation,
# pymikktspace, the reference MikkTSpace of the glTF tests, and their
# third-party glTF asset, from Debian's archive).
# Idempotent: re-running it only checks what is already there.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
TEST=0
[ "${1:-}" = "--test" ] && TEST=1

have_llvm() {
    # Dr.Jit 1.5 crashes with libLLVM <= 16; the package's own search decides.
    "${1:-$PYTHON}" src/mfnormal/_llvm.py >/dev/null 2>&1
}

# 1. A working libLLVM: Debian's libllvm19 when we can install system packages.
if ! have_llvm && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing libllvm19 (Dr.Jit needs libLLVM >= 17)"
    export DEBIAN_FRONTEND=noninteractive
    if ! apt-get install -y -qq libllvm19 >/dev/null 2>&1; then
        apt-get update -qq >/dev/null 2>&1 || true
        apt-get install -y -qq libllvm19 >/dev/null 2>&1 || echo "setup: apt could not install libllvm19"
    fi
fi

# 1b. Headless Chromium for the browser tests (tests/test_report.py, tests/test_docs.py skip without it).
if [ "$TEST" = 1 ] && { ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; } && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing chromium and chromium-driver (browser tests of the HTML report and the docs)"
    export DEBIAN_FRONTEND=noninteractive
    if ! apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1; then
        apt-get update -qq >/dev/null 2>&1 || true
        apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1 || echo "setup: apt could not install chromium"
    fi
fi

# 2. The virtual environment and the package, with the Mitsuba and Dr.Jit it is tested with
#    (scripts/tested-versions.txt; pyproject.toml accepts their patch releases).
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi
EXTRAS=""
[ "$TEST" = 1 ] && EXTRAS="[test,cluster,assets]"
.venv/bin/python -m pip install -q --disable-pip-version-check -c scripts/tested-versions.txt -e ".$EXTRAS" 2>&1 | grep -v '^WARNING: Location' || true

# 2b. The reference MikkTSpace (C) that tests/test_gltf.py compares against; its sdist
#     needs a hand to build (see the script). Without it that one comparison skips.
if [ "$TEST" = 1 ]; then
    bash scripts/install_pymikktspace.sh .venv/bin/python \
        || echo "setup: could not build pymikktspace; tests/test_gltf.py skips its MikkTSpace reference test"
fi

# 2c. A third-party glTF asset (Khronos' ClearCoatTest, from Debian's assimp-testmodels)
#     into tests/data/thirdparty/; without it tests/test_gltf.py skips its tests of it.
if [ "$TEST" = 1 ]; then
    bash scripts/fetch_gltf_asset.sh || true
fi

# 3. No system LLVM: fall back to the libLLVM wheel inside the venv.
if ! have_llvm .venv/bin/python; then
    echo "setup: no system libLLVM >= 17; installing karellen-llvm-core into .venv"
    .venv/bin/python -m pip install -q --disable-pip-version-check karellen-llvm-core 2>&1 | grep -v '^WARNING: Location' || true
fi

# 4. Check: importing mfnormal picks the LLVM and runs a JIT kernel.
.venv/bin/python -c "
import mfnormal, mitsuba as mi, drjit as dr
mi.set_variant('llvm_ad_rgb')
assert dr.minimum(dr.arange(mi.Float, 4), 2.0)[3] == 2.0
print('setup: ok (mitsuba', mi.__version__ + ', libLLVM', mfnormal.LLVM_PATH + ')')
"
