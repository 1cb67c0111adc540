#!/usr/bin/env bash
# The main job on the embedded default: generate the labelled phantom, describe it, ingest it
# into an out-of-core OME-Zarr brick store with its ground truth, and describe the store.
# Real volumes from ../shared/data are ingested too where that folder exists.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-out}
mkdir -p "$OUT"
cargo build --release -q -p neuvolex
NV=./target/release/neuvolex

"$NV" synth phantom --out "$OUT/phantom.nii.gz" --size 128 --force
"$NV" info "$OUT/phantom.nii.gz"
"$NV" ingest "$OUT/phantom.nii.gz" "$OUT/phantom.zarr" --labels "$OUT/phantom_labels.nii.gz" --classes "$OUT/phantom_classes.json" --force
"$NV" info "$OUT/phantom.zarr"
"$NV" train "$OUT/phantom.zarr" --preset fast
"$NV" features "$OUT/phantom.zarr"
# Scribble (simulated S2) and classify every voxel with the learned + local features.
rm -f "$OUT/phantom_scribbles.nii.gz" "$OUT/phantom_scribbles.strokes.json"
"$NV" scribble-sim "$OUT/phantom_labels.nii.gz" --level S2 --seed 0 --out "$OUT/phantom_scribbles.nii.gz"
"$NV" classify "$OUT/phantom.zarr" --scribbles "$OUT/phantom_scribbles.nii.gz" --classes "$OUT/phantom_classes.json" --trees 100 --out "$OUT/phantom_classified.nii.gz" --force

DATA=../shared/data
if [ -d "$DATA" ]; then
  "$NV" ingest "$DATA/tooth/tooth.nhdr" "$OUT/tooth.zarr" --force
  "$NV" info "$OUT/tooth.zarr"
  "$NV" ingest "$DATA/abdomen_ct/ct.nii.gz" "$OUT/abdomen.zarr" --labels "$DATA/abdomen_ct/labels.nii.gz" --force
  "$NV" info "$OUT/abdomen.zarr"
else
  echo "($DATA not found: real-volume part of the demo skipped)"
fi
