"""Classify the abdomen CT from simulated scribbles and show a slice and a rendering.

    target/pyenv/bin/python examples/python/abdomen.py [--napari]

Needs the wheel (deploy/python.sh), nibabel and matplotlib (or napari with --napari), and
../shared/data/abdomen_ct. The scribbles are a few strokes per class on one axial slice,
simulated from the ground truth as `neuvolex scribble-sim --level S1` would paint them.
"""

import sys
from pathlib import Path

import nibabel as nib
import numpy as np

import neuvolex

data = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "abdomen_ct"
store = neuvolex.open(data / "ct.nii.gz", progress=True)  # ingested once, cached
truth = np.asarray(nib.load(data / "labels.nii.gz").dataobj).T  # nibabel's [x, y, z] -> [z, y, x]

# Scribbles on the axial slice where the four classes are largest: a few voxels of each
# class, and of background (255), as a user's strokes would mark them.
z = int(np.argmax([min((truth[k] == c).sum() for c in (1, 2, 3, 4)) for k in range(store.shape[0])]))
scribbles = np.zeros(store.shape, np.uint8)
for c in (0, 1, 2, 3, 4):
    ys, xs = np.nonzero(truth[z] == c)
    pick = np.linspace(0, len(ys) - 1, 20).astype(int)
    scribbles[z, ys[pick], xs[pick]] = 255 if c == 0 else c

labels, proba = store.classify(scribbles, trees=100, progress=True)
for c in (1, 2, 3, 4):
    f1 = 2 * ((labels == c) & (truth == c)).sum() / max(1, (labels == c).sum() + (truth == c).sum())
    print(f"class {c}: F1 {f1:.3f}")
print("most doubtful axial slice:", store.suggest_slice("z"))
store.export("abdomen_labels.nii.gz", force=True)  # the CT's own affine and spacing

if "--napari" in sys.argv:
    import napari

    viewer = napari.Viewer()
    viewer.add_image(store.read(), affine=store.napari_affine, name="CT", contrast_limits=(-300, 500))
    viewer.add_labels(labels, affine=store.napari_affine, name="neuvolex")
    napari.run()
else:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(10, 5))
    ax[0].imshow(store.read()[z], cmap="gray", vmin=-300, vmax=500, origin="lower")
    ax[0].imshow(np.ma.masked_equal(labels[z], 0), cmap="tab10", alpha=0.5, vmin=0, vmax=9, origin="lower")
    ax[0].set_title(f"slice z={z}")
    ax[1].imshow(neuvolex.render(store, labels=labels, view=(30, 20), size=512))
    ax[1].set_title("3-D: classes")
    for a in ax:
        a.axis("off")
    fig.savefig("abdomen.png", dpi=80, bbox_inches="tight")
    print("wrote abdomen.png")
