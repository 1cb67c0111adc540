"""Shared fixtures of the Python tests: the CLI binary, the real data folder, small volumes.

Run by deploy/test.sh against the installed wheel (deploy/python.sh). Tests that need
../shared/data or the CLI skip visibly where they are absent, and fail under CI=true.
"""

import os
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
CI = os.environ.get("CI") == "true"


def need(what: str, ok: bool) -> None:
    """Skips (or fails under CI=true) when `ok` is false."""
    if not ok:
        if CI:
            pytest.fail(f"{what} is required under CI=true")
        pytest.skip(f"SKIP: {what} is absent")


@pytest.fixture(scope="session")
def cli() -> Path:
    """The `neuvolex` binary built by cargo (release)."""
    p = Path(os.environ.get("NEUVOLEX_BIN", ROOT / "target" / "release" / "neuvolex"))
    need(f"the CLI binary {p} (cargo build --release -p neuvolex)", p.exists())
    return p


@pytest.fixture(scope="session")
def data() -> Path:
    """../shared/data beside the repository."""
    p = ROOT.parent / "shared" / "data"
    need(f"{p}", (p / "README.md").exists())
    return p


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    """Each test ingests into its own cache folder."""
    monkeypatch.setenv("NEUVOLEX_CACHE", str(tmp_path / "cache"))


def spheres(shape=(40, 48, 56), seed=0, noise=5.0) -> tuple[np.ndarray, np.ndarray]:
    """A dark volume [z, y, x] with two bright spheres (labels 1 and 2), and its labels."""
    rng = np.random.default_rng(seed)
    z, y, x = np.indices(shape)
    a = (z - shape[0] * 0.5) ** 2 + (y - shape[1] * 0.5) ** 2 + (x - shape[2] * 0.3) ** 2 < 81
    b = (z - shape[0] * 0.5) ** 2 + (y - shape[1] * 0.5) ** 2 + (x - shape[2] * 0.75) ** 2 < 49
    v = np.where(a, 100.0, 0.0) + np.where(b, 60.0, 0.0) + rng.normal(0, noise, shape)
    lab = np.zeros(shape, np.uint8)
    lab[a] = 1
    lab[b] = 2
    return v.astype(np.float32), lab


def strokes(lab: np.ndarray) -> np.ndarray:
    """Scribbles on the middle z-slice: a few voxels of each class and of background (255)."""
    s = np.zeros(lab.shape, np.uint8)
    zc = lab.shape[0] // 2
    for c in np.unique(lab):
        ys, xs = np.nonzero(lab[zc] == c)
        pick = np.linspace(0, len(ys) - 1, min(12, len(ys))).astype(int)
        s[zc, ys[pick], xs[pick]] = 255 if c == 0 else c
    return s
