"""napari reader and sample data of neuvolex: NIfTI, NRRD and OME-Zarr with their geometry.

Each file is ingested once into neuvolex's cached brick store (:func:`neuvolex.open`) and
shown as a layer whose ``affine`` is the store's full voxel-to-world map (scale, translation,
rotation and shear). World coordinates are nibabel's: the file's NIfTI affine maps voxel
(x, y, z) to RAS+ millimetres, and napari's axes are numpy's ``[z, y, x]``, so a layer's world
point ``(w0, w1, w2)`` is nibabel's ``(S, A, R)`` — the RAS+ point with its axes in napari's
reversed order. An LPS NRRD (3D Slicer's) is turned into that RAS+ world by the reader, as
nibabel and ITK's NIfTI writer do. Integer volumes whose name says they are labels
(``label``, ``seg``, ``mask``) become Labels layers, and so do an OME-Zarr's label images.

OME-Zarr 0.5 (Zarr v3) images are ingested by the Rust reader; OME-Zarr 0.4 and earlier
(Zarr v2: ``.zattrs``/``.zarray``, as ome-zarr-py, bioformats2raw and zarr-python 2 write them)
are read here, level 0 of the image and of each label image, each layer on the world its
``coordinateTransformations`` give (the dataset's, then the multiscale's: world = scale *
index + translation, axes z, y, x as napari's). Chunks stored raw, zlib, gzip, bz2 or lzma
need nothing more; Blosc, Zstd and other codecs need ``numcodecs`` (installed with zarr).
Label images of an OME-Zarr written by another tool come along as Labels layers too.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
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


def _name(path: str) -> str:
    name = os.path.basename(path.rstrip("/"))
    for suffix in sorted(_SUFFIXES, key=len, reverse=True):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


def _layers(path: str) -> list[tuple]:
    import neuvolex
    from neuvolex.errors import FileError

    name = _name(path)
    if _is_zarr_v2(path):
        return _ngff_layers(Path(path), name, _V2)
    try:
        store = neuvolex.open(path)
    except FileError:
        if _ngff_v3_attrs(Path(path)) is not None and _zarr3() is not None:
            return _ngff_layers(Path(path), name, _V3)  # what the Rust reader refuses, by zarr-python
        raise
    geometry = {"affine": store.napari_affine}
    data = store.read()
    integer = np.issubdtype(store.dtype, np.integer)
    if integer:
        data = data.astype(store.dtype)
    is_labels = integer and any(w in name.lower() for w in _LABEL_WORDS)
    meta = {"neuvolex_store": store, "neuvolex_source": path}
    # An OME-Zarr 0.5 another tool wrote: the Rust reader placed the image (its level's and
    # its multiscale's transformations); its label images are read here.
    attrs = _ngff_v3_attrs(Path(path)) if os.path.isdir(path) and not _same_folder(store.path, path) else None
    out = [(data, {"name": name, "metadata": meta, **geometry}, "labels" if is_labels else "image")]
    for label in store._native.label_names:
        if label == "classified":
            continue
        values = store._native.read_labels(label).reshape(store.shape)
        kind = np.uint8 if values.max(initial=0) <= 255 else np.uint16
        out.append((values.astype(kind), {"name": f"{name} {label}", **geometry}, "labels"))
    if attrs is not None:
        out.extend(_ngff_label_layers(Path(path), name, _V3))
    return out


def _same_folder(a: str, b: str) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return False


# -- OME-Zarr written by other tools --------------------------------------------------------
# 0.4 and earlier (Zarr v2) are read here; 0.5 (Zarr v3) images by the Rust reader, their
# label images by zarr-python where installed (else by the Rust reader).


def _json(path: Path) -> Any:
    from neuvolex.errors import FileError

    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise FileError(f"{path}: cannot read its Zarr metadata: {e}") from e


def _is_zarr_v2(path: str) -> bool:
    """A Zarr v2 folder (OME-Zarr 0.4 or earlier): ``.zgroup``/``.zattrs``/``.zarray``, no
    ``zarr.json``."""
    p = Path(path)
    return p.is_dir() and not (p / "zarr.json").exists() and any((p / f).is_file() for f in (".zgroup", ".zattrs", ".zarray"))


def _zarr3() -> Any:
    """zarr-python 3 (which reads Zarr v3), or None."""
    try:
        import zarr
    except ImportError:
        return None
    return zarr if int(zarr.__version__.split(".")[0]) >= 3 else None


class _V2:
    """Zarr v2 groups and arrays (OME-Zarr 0.4 and earlier)."""

    @staticmethod
    def attrs(group: Path) -> dict:
        return _json(group / ".zattrs") if (group / ".zattrs").is_file() else {}

    @staticmethod
    def read(array: Path) -> np.ndarray:
        return _read_v2_array(array)


class _V3:
    """Zarr v3 groups and arrays (OME-Zarr 0.5): the ``ome`` attributes of ``zarr.json``."""

    @staticmethod
    def attrs(group: Path) -> dict:
        return _ngff_v3_attrs(group) or {}

    @staticmethod
    def read(array: Path) -> np.ndarray:
        zarr = _zarr3()
        if zarr is not None:
            return np.asarray(zarr.open_array(str(array), mode="r")[...])
        import neuvolex

        store = neuvolex.open(str(array))  # the Rust reader (a bare z, y, x array)
        data = store.read()
        return data.astype(store.dtype) if np.issubdtype(store.dtype, np.integer) else data


def _ngff_v3_attrs(group: Path) -> dict | None:
    """The OME attributes (``ome``) of a Zarr v3 group, or None where it has none."""
    try:
        node = json.loads((group / "zarr.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    attrs = node.get("attributes") or {}
    ome = attrs.get("ome") if isinstance(attrs.get("ome"), dict) else attrs
    return ome if ("multiscales" in ome or "labels" in ome) else None


def _ngff_layers(root: Path, name: str, fmt: type) -> list[tuple]:
    """The image (level 0) and the label images of an OME-Zarr store read here."""
    meta = {"neuvolex_source": str(root)}
    if (root / ".zarray").is_file():  # a bare Zarr v2 array: voxel units
        array = _read_v2_array(root)
        data = _squeeze_zyx(root, array, ["t", "c", "z", "y", "x"][-array.ndim :])
        return [(data, {"name": name, "metadata": meta, "affine": np.eye(4)}, "image")]
    data, affine = _ngff_image(root, fmt)
    integer = np.issubdtype(data.dtype, np.integer)
    is_labels = integer and any(w in name.lower() for w in _LABEL_WORDS)
    out = [(data, {"name": name, "metadata": meta, "affine": affine}, "labels" if is_labels else "image")]
    return out + _ngff_label_layers(root, name, fmt)


def _ngff_label_layers(root: Path, name: str, fmt: type) -> list[tuple]:
    """The label images listed in ``labels/`` as Labels layers, each on its own world; one
    that cannot be read is left out with a warning (napari shows it) and the rest open."""
    import warnings

    from neuvolex.errors import Error

    labels = root / "labels"
    if not labels.is_dir():
        return []
    out = []
    for label in fmt.attrs(labels).get("labels") or []:
        try:
            values, affine = _ngff_image(labels / str(label), fmt)
        except (Error, OSError, ValueError) as e:
            warnings.warn(f"neuvolex: label image {label!r} of {root} left out: {e}", stacklevel=2)
            continue
        if not np.issubdtype(values.dtype, np.integer):
            values = values.astype(np.int32)
        out.append((values, {"name": f"{name} {label}", "affine": affine}, "labels"))
    return out


def _ngff_image(group: Path, fmt: type) -> tuple[np.ndarray, np.ndarray]:
    """Level 0 of the multiscale image of `group` as ``[z, y, x]``, and its napari affine."""
    from neuvolex.errors import FileError

    multiscales = fmt.attrs(group).get("multiscales")
    if not multiscales:
        raise FileError(f"{group}: a Zarr group without OME-Zarr multiscales metadata")
    ms = multiscales[0]
    array = fmt.read(group / _ngff_dataset(group, ms)["path"])
    axes = ms.get("axes")
    if axes is not None and array.ndim < len(axes):  # the Rust reader drops size-1 leading axes
        array = array.reshape((1,) * (len(axes) - array.ndim) + array.shape)
    names = _ngff_axes(ms, array.ndim)
    if len(names) != array.ndim:
        raise FileError(f"{group}: {len(names)} axes for an array of {array.ndim} dimensions")
    return _squeeze_zyx(group, array, names), _ngff_affine(group, ms, array.ndim)


def _ngff_dataset(group: Path, ms: dict) -> dict:
    """Level 0 of a multiscales entry, its path checked to lie inside the group."""
    from neuvolex.errors import FileError

    datasets = ms.get("datasets") or []
    rel = datasets[0].get("path") if datasets and isinstance(datasets[0], dict) else None
    if not isinstance(rel, str) or not rel or rel.startswith("/") or any(c in ("", ".", "..") for c in rel.split("/")):
        raise FileError(f"{group}: dataset path {rel!r} must name an array inside the group")
    return datasets[0]


def _ngff_axes(ms: dict, ndim: int) -> list[str]:
    axes = ms.get("axes")
    if axes is None:  # 0.1 and 0.2: always t, c, z, y, x
        return ["t", "c", "z", "y", "x"][-ndim:]
    return [str(a.get("name", "") if isinstance(a, dict) else a).lower() for a in axes]


def _ngff_affine(group: Path, ms: dict, ndim: int) -> np.ndarray:
    """napari's affine of level 0: its dataset's coordinate transformations, then the
    multiscale's (NGFF 0.4 and 0.5), for the last three axes (z, y, x)."""
    from neuvolex.errors import FileError

    scale = np.ones(ndim)
    translation = np.zeros(ndim)
    for transforms in (_ngff_dataset(group, ms).get("coordinateTransformations"), ms.get("coordinateTransformations")):
        for t in transforms or []:
            kind = t.get("type")
            if kind == "identity":
                continue
            values = t.get(kind)
            if kind not in ("scale", "translation") or values is None:
                raise FileError(f"{group}: coordinate transformation {t} is not supported (scale and translation are)")
            values = np.asarray(values, dtype=np.float64)
            if values.shape != (ndim,):
                raise FileError(f"{group}: {kind} {values.tolist()} does not have {ndim} values")
            if kind == "scale":
                scale, translation = scale * values, translation * values
            else:
                translation = translation + values
    affine = np.eye(4)
    affine[:3, :3] = np.diag(scale[-3:])
    affine[:3, 3] = translation[-3:]
    return affine


def _squeeze_zyx(where: Path, array: np.ndarray, names: list[str]) -> np.ndarray:
    from neuvolex.errors import FileError

    if array.ndim < 3 or names[-3:] != ["z", "y", "x"]:
        raise FileError(f"{where}: axes {names} do not end in z, y, x (a 3-D volume)")
    if any(n != 1 for n in array.shape[:-3]):
        raise FileError(
            f"{where}: shape {array.shape} (axes {names}): only single-channel, single-time volumes are supported"
        )
    return array.reshape(array.shape[-3:])


def _v2_codec(config: Any, where: Path) -> Callable[[bytes], bytes]:
    """The decoder of a Zarr v2 compressor or filter configuration."""
    import bz2
    import gzip
    import lzma
    import zlib

    from neuvolex.errors import FileError

    stdlib = {"zlib": zlib.decompress, "gzip": gzip.decompress, "bz2": bz2.decompress, "lzma": lzma.decompress}
    codec = config.get("id") if isinstance(config, dict) else None
    if codec in stdlib:
        return stdlib[codec]
    try:
        import numcodecs
    except ImportError:
        raise FileError(
            f"{where}: its chunks are {codec}-encoded: install numcodecs (pip install zarr) to read them"
        ) from None
    decoder = numcodecs.get_codec(dict(config))
    return lambda raw: decoder.decode(raw)


def _read_v2_array(path: Path) -> np.ndarray:
    """A whole Zarr v2 array (``.zarray`` and its chunk files) as numpy; a chunk never
    written is the fill value."""
    from neuvolex.errors import FileError

    meta = _json(path / ".zarray")
    if meta.get("zarr_format") != 2:
        raise FileError(f"{path}: zarr_format {meta.get('zarr_format')!r} in .zarray is not 2")
    try:
        dtype = np.dtype(meta["dtype"])
        shape = tuple(int(n) for n in meta["shape"])
        chunks = tuple(int(n) for n in meta["chunks"])
    except (KeyError, TypeError, ValueError) as e:
        raise FileError(f"{path}: bad .zarray ({e})") from e
    if dtype.kind not in "biuf" or len(chunks) != len(shape) or any(c <= 0 for c in chunks):
        raise FileError(f"{path}: dtype {meta['dtype']} with chunks {chunks} of shape {shape} is not a volume")
    order = meta.get("order", "C")
    separator = meta.get("dimension_separator") or "."
    decoders = [_v2_codec(f, path) for f in reversed(meta.get("filters") or [])]
    if meta.get("compressor") is not None:
        decoders.insert(0, _v2_codec(meta["compressor"], path))
    fill = meta.get("fill_value")
    fill = 0 if fill is None else {"NaN": np.nan, "Infinity": np.inf, "-Infinity": -np.inf}.get(fill, fill)
    out = np.full(shape, fill, dtype=dtype)
    for index in np.ndindex(*[-(-s // c) for s, c in zip(shape, chunks)]):
        chunk_file = path / (separator.join(str(i) for i in index) if index else "0")
        if not chunk_file.is_file():
            continue  # never written: the fill value
        raw = chunk_file.read_bytes()
        for decode in decoders:
            raw = decode(raw)
        raw = memoryview(raw).cast("B")
        if raw.nbytes != dtype.itemsize * int(np.prod(chunks)):
            raise FileError(f"{chunk_file}: {raw.nbytes} bytes, expected a chunk {chunks} of {dtype}")
        chunk = np.frombuffer(raw, dtype=dtype).reshape(chunks, order=order)
        where = tuple(slice(i * c, min((i + 1) * c, s)) for i, c, s in zip(index, chunks, shape))
        out[where] = chunk[tuple(slice(0, w.stop - w.start) for w in where)]
    return out.astype(dtype.newbyteorder("="), copy=False)


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
