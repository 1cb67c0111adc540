#!/usr/bin/env python3
"""Interactive rounds through the Python package's Session on the brain MRI crop.

The crop of `cargo bench --bench rounds` (160x232x160 voxels of ../shared/data/brain_mri from
(x, y, z) = (48, 12, 48), 5.9 M voxels), ingested with `neuvolex.from_array`. Round 0: S1
scribbles of the crop's ground truth (`neuvolex scribble-sim`, seed 0). Each later round, a
robot adds one axial slice's corrections, as a user would: on the slice (a new one each round,
spread over the volume) up to 400 voxels the shown labels get wrong, painted with their true
label (background as 255). Every round is `session.classify(scribbles, trees=N,
probabilities=False)`, timed whole in this process: the forest trained, every brick predicted,
the prior and growth, the stability rule, the labels handed back. Round 0 computes the features
(cold); later rounds read them from the session. `--store-classify` also times one
`Store.classify` of the last scribbles (features recomputed) for comparison.

    target/pyenv/bin/python benches/python_session.py [--rounds 8] [--trees 32] [--store-classify]

Needs the wheel (deploy/python.sh), the CLI (cargo build --release -p neuvolex) and nibabel.
"""

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import nibabel as nib
import numpy as np

import neuvolex

ROOT = Path(__file__).resolve().parents[1]
LO, SIZE = (48, 12, 48), (160, 232, 160)  # (x, y, z), as benches/rounds.rs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--trees", type=int, default=32, help="the service's trees on 5.9 M voxels (MIN_TREES)")
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    ap.add_argument("--store-classify", action="store_true")
    a = ap.parse_args()
    img_p = Path(a.data) / "brain_mri" / "t1_norm.nii.gz"
    lab_p = Path(a.data) / "brain_mri" / "labels.nii.gz"
    if not (img_p.exists() and lab_p.exists()):
        print(f"SKIP: {img_p.parent} is absent")
        return 0
    cli = Path(os.environ.get("NEUVOLEX_BIN", ROOT / "target" / "release" / "neuvolex"))
    img, lab = nib.load(img_p), nib.load(lab_p)
    box = tuple(slice(lo, lo + n) for lo, n in zip(LO, SIZE))
    values = np.ascontiguousarray(np.asarray(img.dataobj)[box].T.astype(np.float32))  # [z, y, x]
    truth_xyz = np.asarray(lab.dataobj)[box].astype(np.uint8)
    truth = np.ascontiguousarray(truth_xyz.T)
    spacing = tuple(float(s) for s in img.header.get_zooms()[:3])[::-1]
    with tempfile.TemporaryDirectory() as tmp:
        nib.save(nib.Nifti1Image(truth_xyz, np.diag([*spacing[::-1], 1.0])), f"{tmp}/truth.nii.gz")
        subprocess.run([cli, "--quiet", "scribble-sim", f"{tmp}/truth.nii.gz", "--level", "S1", "--out", f"{tmp}/s1.nii.gz"], check=True)
        scribbles = np.ascontiguousarray(np.asarray(nib.load(f"{tmp}/s1.nii.gz").dataobj).T.astype(np.uint8))
        store = neuvolex.from_array(values, spacing=spacing, store=f"{tmp}/crop.zarr")
        session = store.session(cache_bytes=4 << 30)
        print(f"brain MRI crop {SIZE[0]}x{SIZE[1]}x{SIZE[2]} ({values.size / 1e6:.1f} M voxels), {a.trees} trees, "
              f"{store.features().channels} feature channels")
        seconds, held, labels = [], [], None
        slices = np.linspace(20, SIZE[2] - 20, a.rounds).astype(int)
        rng = np.random.default_rng(0)
        for r in range(a.rounds + 1):
            if r > 0:
                z = int(slices[r - 1])
                wrong = np.argwhere(labels[z] != truth[z])
                pick = wrong[rng.permutation(len(wrong))[:400]]
                for y, x in pick:
                    t = truth[z, y, x]
                    scribbles[z, y, x] = 255 if t == 0 else t
            t0 = time.perf_counter()
            labels, _ = session.classify(scribbles, trees=a.trees, probabilities=False)
            seconds.append(time.perf_counter() - t0)
            held.append(session.last_report["voxels_held"])
            print(f"round {r}: {seconds[-1]:.2f} s, held {held[-1]}, features kept {session.cached_bytes / 2**20:.0f} MiB", flush=True)
        later = seconds[1:]
        print(f"round 0 (cold features): {seconds[0]:.2f} s; rounds 1-{a.rounds}: median "
              f"{statistics.median(later):.2f} s [{min(later):.2f}-{max(later):.2f}]")
        if a.store_classify:
            t0 = time.perf_counter()
            store.classify(scribbles, trees=a.trees, probabilities=False)
            print(f"Store.classify of the last scribbles (features recomputed): {time.perf_counter() - t0:.2f} s")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
