#!/usr/bin/env bash
# The whole test suite, on a fresh machine: a small Python environment for the checks that use
# the standard readers (mcap, trimesh), the release binaries the end-to-end tests start, then
# every test of the workspace.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

# Debian packages the tests drive for real: the DEM engines our STL must import, the
# browser that renders report.html (tests/report.rs), and Gwyddion, an independent reader of
# our X3P, GSF and TIFF (common/io/tests/writers_read_back.rs; `--convert-to-gwy` runs
# without a display, no xvfb needed).
missing=()
command -v gwyddion >/dev/null || missing+=(gwyddion)
command -v liggghts >/dev/null || missing+=(liggghts)
command -v mpirun >/dev/null || missing+=(openmpi-bin)
command -v yade >/dev/null || missing+=(yade)
[ -x /usr/bin/chromium ] || missing+=(chromium)
if [ ${#missing[@]} -gt 0 ]; then
    echo "test.sh: installing ${missing[*]} (apt-get)"
    SUDO=""
    [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${missing[@]}" >/dev/null
fi

VENV=.test-venv
if [ ! -x "$VENV/bin/python" ] || ! "$VENV/bin/python" -c 'import mcap, trimesh, numpy, pywt, surfalize, h5py, scipy, zarr, websockets, SurfaceTopography' 2>/dev/null; then
    echo "test.sh: creating $VENV (mcap, trimesh, numpy, PyWavelets, surfalize, h5py, scipy, zarr, websockets, SurfaceTopography)"
    python3 -m venv "$VENV"
    "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --only-binary=:all: \
        -r scripts/test-requirements.txt
fi
export SURFSTREAM_PYTHON="$PWD/$VENV/bin/python"
# The independent readers of our written files, installed above: the tests that use them
# fail, not skip, when one is missing.
export SURFSTREAM_SURFTOPO_PYTHON="$SURFSTREAM_PYTHON"
SURFSTREAM_GWYDDION="$(command -v gwyddion)"
export SURFSTREAM_GWYDDION
export SURFSTREAM_REQUIRE_INDEPENDENT_READERS=1
# The specimens the tests need are in tests/data/specimens; a few real files whose licences
# keep them out of the repository (GPL-3 / LGPL-3: tests/data/specimens/README.md) are checked
# too when a specimen folder is beside the clone (../shared/specimens, as on CI) or named by
# SURFSTREAM_SPECIMENS; without one those few tests say they skipped.
if [ -z "${SURFSTREAM_SPECIMENS:-}" ] && [ -d ../shared/specimens ]; then
    SURFSTREAM_SPECIMENS="$(cd ../shared/specimens && pwd)"
    export SURFSTREAM_SPECIMENS
    echo "test.sh: also checking the specimens in $SURFSTREAM_SPECIMENS"
fi

# Every crate's modules import downwards only (docs/architecture.md §11): a cycle in the code
# fails here; the mesher's doc links and tests too.
"$SURFSTREAM_PYTHON" scripts/module_graph.py nodes/mesher/src >/dev/null ||
    { echo "test.sh: nodes/mesher/src has an import cycle (python3 scripts/module_graph.py nodes/mesher/src)"; exit 1; }
for src in common/*/src nodes/*/src launch/src python/src; do
    "$SURFSTREAM_PYTHON" scripts/module_graph.py --code-only --no-tests "$src" >/dev/null ||
        { echo "test.sh: $src has an import cycle (python3 scripts/module_graph.py --code-only --no-tests $src)"; exit 1; }
done

cargo build --release --workspace --bins
# PyWavelets parity goldens (every base, mode, odd/even size, level) for nodes/wavelet's tests.
"$SURFSTREAM_PYTHON" scripts/gen_wavelet_golden.py target/wavelet-golden
export SURFSTREAM_WAVELET_GOLDEN="$PWD/target/wavelet-golden"
cargo test --release --workspace

# The Python package (python/, pyo3 + maturin from PyPI): installed into the test venv as a
# user installs it (pip install ./python, a release build sharing target/) and tested with
# pytest against the CLI binary just built and the specimens in tests/data/specimens
# (SURFSTREAM_SPECIMENS, when set, is looked in first).
"$SURFSTREAM_PYTHON" -c 'import pytest' 2>/dev/null ||
    "$SURFSTREAM_PYTHON" -m pip install --quiet --disable-pip-version-check 'pytest==9.2.0'
"$SURFSTREAM_PYTHON" -m pip install --quiet --disable-pip-version-check ./python
SURFSTREAM_CLI="$PWD/target/release/surfstream" "$SURFSTREAM_PYTHON" -m pytest -q python/tests
