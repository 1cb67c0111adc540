#!/usr/bin/env bash
# The Python package: a venv under target/pyenv with what the Python and napari tests need
# (maturin, pytest, pytest-qt, napari with PyQt5, nibabel, tqdm, zarr: the napari reader test of
# OME-Zarr written by zarr-python) and Xvfb, then the `neuvolex` wheel
# built from python/ with maturin (release, against the workspace's target/) and installed.
#   deploy/python.sh          set up (once) and build and install the wheel
#   deploy/python.sh venv     only the venv
#   deploy/python.sh install  as a user installs it: `pip install ./python` into a fresh venv
#                             (target/pyfresh), then import it and run a classification there
#   deploy/python.sh sdist    build the sdist and install it into a fresh venv (a full build of
#                             every crate from the sdist's own copy: minutes; not part of CI)
# The wheel (abi3: one wheel for CPython 3.10 and later) lands in target/wheels/.
set -euo pipefail
cd "$(dirname "$0")/.."
py=target/pyenv/bin/python
need="nibabel maturin pytest pytest-qt napari[pyqt5] tqdm zarr"
if ! [ -x "$py" ]; then
  python3 -m venv target/pyenv
fi
if ! "$py" -c 'import nibabel, maturin, pytest, pytestqt, napari, tqdm, zarr' >/dev/null 2>&1; then
  echo "installing the Python test tools into target/pyenv (${need})"
  # shellcheck disable=SC2086
  "$py" -m pip install -q --disable-pip-version-check $need
fi
# napari's canvas needs OpenGL through an X server: headless, the napari test starts Xvfb
# (with the xcb libraries Qt's platform plugins load).
if ! command -v Xvfb >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && SUDO="sudo -n"
  pkgs="xvfb xauth libxcb-icccm4 libxcb-keysyms1 libxcb-xinerama0 libxcb-image0 libxcb-render-util0 libxcb-randr0 libxcb-shape0 libxkbcommon-x11-0 libgl1 libegl1"
  echo "installing Xvfb for the napari test"
  # shellcheck disable=SC2086
  $SUDO apt-get install -y -q $pkgs >/dev/null 2>&1 ||
    { $SUDO apt-get update -q >/dev/null 2>&1 && $SUDO apt-get install -y -q $pkgs >/dev/null 2>&1; } ||
    echo "could not install Xvfb: the napari test will skip (fail under CI=true)"
fi
[ "${1:-}" = "venv" ] && exit 0
# A fresh venv as a user makes one, and an import of what it installed (not of python/).
check_fresh() {
  local py_fresh="$PWD/target/pyfresh/bin/python"
  (cd / && "$py_fresh" -c '
import numpy as np, neuvolex
assert neuvolex.__file__.find("site-packages") > 0, neuvolex.__file__
v = np.zeros((24, 24, 24), np.float32); v[6:18, 6:18, 6:18] = 100
s = np.zeros(v.shape, np.uint8); s[12, 10:14, 10:14] = 1; s[12, 0:3, 0:3] = 255
labels, _ = neuvolex.from_array(v).classify(s, trees=5)
assert labels[12, 12, 12] == 1 and labels[1, 1, 1] == 0
print("imported", neuvolex.__version__, "from", neuvolex.__file__)')
}
if [ "${1:-}" = "install" ] || [ "${1:-}" = "sdist" ]; then
  rm -rf target/pyfresh
  python3 -m venv target/pyfresh
  if [ "$1" = "install" ]; then
    # pip builds python/ in place with maturin (PEP 517): cargo shares the workspace's target/
    # (CARGO_TARGET_DIR), so an up-to-date build costs only the link and the packaging.
    CARGO_TARGET_DIR="$PWD/target" target/pyfresh/bin/pip install -q --disable-pip-version-check ./python
  else
    VIRTUAL_ENV="$PWD/target/pyenv" PATH="$PWD/target/pyenv/bin:$PATH" \
      target/pyenv/bin/maturin sdist -m python/Cargo.toml -o target/wheels
    sdist=$(ls -t target/wheels/neuvolex-*.tar.gz | head -1)
    CARGO_TARGET_DIR="$PWD/target/sdist-build" target/pyfresh/bin/pip install -q --disable-pip-version-check "$sdist"
  fi
  check_fresh
  exit 0
fi
# maturin's own builds set PYO3_BUILD_EXTENSION_MODULE (no libpython link).
VIRTUAL_ENV="$PWD/target/pyenv" PATH="$PWD/target/pyenv/bin:$PATH" \
  target/pyenv/bin/maturin build --release -m python/Cargo.toml -o target/wheels -q
whl=$(ls -t target/wheels/neuvolex-*.whl | head -1)
"$py" -m pip install -q --disable-pip-version-check --force-reinstall --no-deps "$whl"
echo "installed ${whl} into target/pyenv"
