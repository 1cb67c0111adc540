"""napari reader and sample data of neuvolex: NIfTI, NRRD and OME-Zarr with their geometry.

Each file is ingested once into neuvolex's cached brick store (:func:`neuvolex.open`) and
shown as a layer whose ``affine`` is the store's full voxel-to-world map (scale, translation,
rotation and shear). World coordinates are nibabel's: the file's NIfTI affine maps voxel
(x, y, z) to RAS+ millimetres, and napari's axes are numpy's ``[z, y, x]``, so a layer's world
point ``(w0, w1, w2)`` is nibabel's ``(S, A, R)`` — the RAS+ point with its axes in napari's
reversed order. An LPS NRRD (3D Slicer's) is turned into that RAS+ world by the reader, as
nibabel and ITK's NIfTI writer do. Integer volumes whose name says they are labels
(``label``, ``seg``, ``mask``) become Labels layers, and so do an OME-Zarr's label images.
"""

from __future__ import annotations

import os
from typing import Any, Callable

import numpy as np

_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".zarr", ".ome.zarr")
_LABEL_WORDS = ("label", "seg", "mask")


def _is_volume(path: str) -> bool:
    p = path.rstrip("/").lower()
    return p.endswith(_SUFFIXES)


def get_reader(path: Any) -> Callable[[Any], list] | None:
    """npe2 reader hook: a reader for one NIfTI, NRRD or OME-Zarr path, else ``None``."""
    if isinstance(path, (list, tuple)):
        if not path or not all(isinstance(p, (str, os.PathLike)) and _is_volume(os.fspath(p)) for p in path):
            return None
    elif not (isinstance(path, (str, os.PathLike)) and _is_volume(os.fspath(path))):
        return None
    return read


def read(path: Any) -> list[tuple]:
    """Layer data tuples ``(data, kwargs, "image" | "labels")`` of each path."""
    paths = path if isinstance(path, (list, tuple)) else [path]
    layers: list[tuple] = []
    for p in paths:
        layers.extend(_layers(os.fspath(p)))
    return layers


def _layers(path: str) -> list[tuple]:
    import neuvolex

    store = neuvolex.open(path)
    name = os.path.basename(path.rstrip("/"))
    for suffix in sorted(_SUFFIXES, key=len, reverse=True):
        if name.lower().endswith(suffix):
            name = name[: -len(suffix)]
            break
    geometry = {"affine": store.napari_affine}
    data = store.read()
    integer = np.issubdtype(store.dtype, np.integer)
    if integer:
        data = data.astype(store.dtype)
    is_labels = integer and any(w in name.lower() for w in _LABEL_WORDS)
    meta = {"neuvolex_store": store, "neuvolex_source": path}
    out = [(data, {"name": name, "metadata": meta, **geometry}, "labels" if is_labels else "image")]
    for label in store._native.label_names:
        if label == "classified":
            continue
        values = store._native.read_labels(label).reshape(store.shape)
        kind = np.uint8 if values.max(initial=0) <= 255 else np.uint16
        out.append((values.astype(kind), {"name": f"{name} {label}", **geometry}, "labels"))
    return out


def phantom() -> list[tuple]:
    """npe2 sample data: the generated phantom (a CT-like volume in HU) and its ground truth."""
    import neuvolex

    store, truth = neuvolex.sample_phantom(96)
    geometry = {"affine": store.napari_affine}
    image = store.read().astype(store.dtype)
    return [
        (image, {"name": "neuvolex phantom", "metadata": {"neuvolex_store": store}, "contrast_limits": (-200, 300), **geometry}, "image"),
        (truth, {"name": "neuvolex phantom truth", "opacity": 0.4, "visible": False, **geometry}, "labels"),
    ]
