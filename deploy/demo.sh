#!/usr/bin/env bash
# The main job on the embedded default: generate the labelled phantom, describe it, ingest it
# into an out-of-core OME-Zarr brick store with its ground truth, describe the store, train the
# INR, scribble, classify, and render the class probabilities to PNG.
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
# Render the class probabilities (the paper's probabilistic mode) and the plain intensity TF.
"$NV" render "$OUT/phantom.zarr" --probs --mode prob --view 30,20 --size 512 --out "$OUT/phantom_prob.png"
"$NV" render "$OUT/phantom.zarr" --probs --mode prob-intensity --view 30,20 --size 512 --out "$OUT/phantom_prob_intensity.png"
"$NV" render "$OUT/phantom.zarr" --tf preset:ct-bone --view 30,20 --size 512 --out "$OUT/phantom_bone.png"
# Recommend viewpoints from the stored INR features (mini-batch k-means, 50 clusters, 1800 views).
"$NV" viewpoints "$OUT/phantom.zarr" --stored-features --algorithm minibatch --size 256 --out "$OUT/phantom_views"

DATA=../shared/data
if [ -d "$DATA" ]; then
  "$NV" ingest "$DATA/tooth/tooth.nhdr" "$OUT/tooth.zarr" --force
  "$NV" info "$OUT/tooth.zarr"
  "$NV" ingest "$DATA/abdomen_ct/ct.nii.gz" "$OUT/abdomen.zarr" --labels "$DATA/abdomen_ct/labels.nii.gz" --force
  "$NV" info "$OUT/abdomen.zarr"
  "$NV" render "$OUT/abdomen.zarr" --tf preset:ct-bone --view 20,10 --size 512 --out "$OUT/abdomen_bone.png"
  "$NV" render "$OUT/abdomen.zarr" --labels ground_truth --mode prob --view 20,10 --size 512 --out "$OUT/abdomen_truth.png"
else
  echo "($DATA not found: real-volume part of the demo skipped)"
fi
