#!/usr/bin/env python3
"""The Python API against the CLI on the same classification: its overhead.

Both sides classify the same store contents from the same scribbles with the same forest
(trees, seed), features, prior and threads (rayon's pool over every core), and write the same
outputs into their store (probabilities, label vectors, the label image). Timed:
  cli     `neuvolex --quiet classify STORE --scribbles S1.nii.gz --trees N`, the whole process
          (start, reading the scribbles file, the pipeline), as a user runs it;
  python  `store.classify(scribbles, trees=N, probabilities=False)` in this process (the
          scribble array converted, the pipeline, the labels handed back as numpy);
  python+p the same returning the class probabilities as well (an extra read the CLI does not
          do, shown apart).
Rounds interleave the sides. The labels are checked equal first (bit for bit).

    target/pyenv/bin/python benches/python_overhead.py [--rounds 5] [--trees 100]
        [--volume ../shared/data/abdomen_ct/ct.nii.gz --labels ../shared/data/abdomen_ct/labels.nii.gz]

Needs the wheel (deploy/python.sh) and the CLI (cargo build --release -p neuvolex).
"""

import argparse
import os
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


def spread(v):
    return f"{statistics.median(v):.3f} [{min(v):.3f}-{max(v):.3f}]"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    data = ROOT.parent / "shared" / "data" / "abdomen_ct"
    ap.add_argument("--volume", default=str(data / "ct.nii.gz"))
    ap.add_argument("--labels", default=str(data / "labels.nii.gz"))
    ap.add_argument("--level", default="S1")
    ap.add_argument("--trees", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--cli", default=str(ROOT / "target" / "release" / "neuvolex"))
    a = ap.parse_args()
    for p in (a.volume, a.labels, a.cli):
        if not Path(p).exists():
            print(f"python_overhead: {p} is missing", file=sys.stderr)
            return 2
    with tempfile.TemporaryDirectory(prefix="neuvolex-pybench-") as tmp:
        tmp = Path(tmp)
        cli_store, py_store = tmp / "cli.zarr", tmp / "py.zarr"
        scr_path = tmp / "scribbles.nii.gz"
        run = lambda *args: subprocess.run([a.cli, "--quiet", *map(str, args)], check=True, capture_output=True)
        run("ingest", a.volume, cli_store)
        run("scribble-sim", a.labels, "--level", a.level, "--out", scr_path)
        store = neuvolex.open(a.volume, store=py_store)
        scribbles = np.asarray(nib.load(scr_path).dataobj).T
        cli_cmd = ["classify", cli_store, "--scribbles", scr_path, "--trees", a.trees]
        # Equivalence (and warm-up): the same labels from both.
        run(*cli_cmd, "--out", tmp / "cli.nii.gz")
        expect = np.asarray(nib.load(tmp / "cli.nii.gz").dataobj).T
        labels, _ = store.classify(scribbles, trees=a.trees, probabilities=False)
        same = np.array_equal(labels, expect)
        print(f"volume {a.volume}: {store.shape} (z, y, x), scribbles {a.level}: {int((scribbles > 0).sum())} voxels, "
              f"{a.trees} trees, {os.cpu_count()} cores; labels equal to the CLI's: {same}")
        if not same:
            print(f"  differing voxels: {int((labels != expect).sum())}", file=sys.stderr)
            return 1
        t_cli, t_py, t_pyp = [], [], []
        for r in range(a.rounds):
            t = time.perf_counter()
            run(*cli_cmd)
            t_cli.append(time.perf_counter() - t)
            t = time.perf_counter()
            store.classify(scribbles, trees=a.trees, probabilities=False)
            t_py.append(time.perf_counter() - t)
            t = time.perf_counter()
            store.classify(scribbles, trees=a.trees, probabilities=True)
            t_pyp.append(time.perf_counter() - t)
            print(f"round {r}: cli {t_cli[-1]:.3f} s, python {t_py[-1]:.3f} s "
                  f"({100 * (t_py[-1] / t_cli[-1] - 1):+.1f} %), python+probabilities {t_pyp[-1]:.3f} s")
        ratios = [p / c for p, c in zip(t_py, t_cli)]
        over = [100 * (r - 1) for r in ratios]
        print(f"cli               {spread(t_cli)} s")
        print(f"python            {spread(t_py)} s")
        print(f"python+proba      {spread(t_pyp)} s")
        print(f"overhead (python/cli - 1, per round): median {statistics.median(over):+.1f} % "
              f"[{min(over):+.1f} to {max(over):+.1f} %]")
        print(f"summary: python vs cli classify | {spread(t_py)} s | {spread(t_cli)} s | "
              f"overhead {statistics.median(over):+.1f} % [{min(over):+.1f}, {max(over):+.1f}] | labels equal")
    return 0


if __name__ == "__main__":
    sys.exit(main())
