#!/usr/bin/env bash
# The Python package: a venv under target/pyenv with what the Python and napari tests need
# (maturin, pytest, pytest-qt, napari with PyQt5, nibabel, tqdm) and Xvfb, then the `neuvolex` wheel
# built from python/ with maturin (release, against the workspace's target/) and installed.
#   deploy/python.sh          set up (once) and build and install the wheel
#   deploy/python.sh venv     only the venv
# The wheel lands in target/wheels/.
set -euo pipefail
cd "$(dirname "$0")/.."
py=target/pyenv/bin/python
need="nibabel maturin pytest pytest-qt napari[pyqt5] tqdm"
if ! [ -x "$py" ]; then
  python3 -m venv target/pyenv
fi
if ! "$py" -c 'import nibabel, maturin, pytest, pytestqt, napari, tqdm' >/dev/null 2>&1; then
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
# maturin's own builds set PYO3_BUILD_EXTENSION_MODULE (no libpython link).
VIRTUAL_ENV="$PWD/target/pyenv" PATH="$PWD/target/pyenv/bin:$PATH" \
  target/pyenv/bin/maturin build --release -m python/Cargo.toml -o target/wheels -q
whl=$(ls -t target/wheels/neuvolex-*.whl | head -1)
"$py" -m pip install -q --disable-pip-version-check --force-reinstall --no-deps "$whl"
echo "installed ${whl} into target/pyenv"
