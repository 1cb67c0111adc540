"""neuvolex from Python: out-of-core volume exploration with learned features.

Arrays are numpy-ordered ``a[z, y, x]`` (napari's order). Per-axis tuples (``spacing``,
``origin``, ``shape``) follow the same (z, y, x) order, like napari's ``scale`` and
``translate``. ``Store.affine`` is the NIfTI voxel-to-world matrix, acting on (x, y, z, 1) as
nibabel's ``img.affine`` does; ``Store.napari_affine`` is the same map for napari's axes.

    import neuvolex
    store = neuvolex.open("ct.nii.gz")             # ingested once into a cached brick store
    labels, proba = store.classify(scribbles)      # scribbles: int array [z, y, x], 0 = none
    image = neuvolex.render(store, labels=labels)  # (H, W, 4) uint8

Long calls release the GIL and run on a worker thread; Ctrl-C cancels them at the next brick.
Errors are ``ValueError`` (bad arguments or data, naming the argument) or ``RuntimeError``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import weakref
from pathlib import Path
from typing import Any, Callable, Iterable, Optional, Sequence, Union

import numpy as np

from . import _native

__all__ = ["Store", "FeatureArray", "open", "from_array", "render", "__version__"]
__version__ = _native.__version__

PathLike = Union[str, "os.PathLike[str]"]
Progress = Union[None, bool, Callable[[int, int, str], Any]]

_AXES = {"z": "z", "y": "y", "x": "x", 0: "z", 1: "y", 2: "x"}


def _progress(progress: Progress, what: str):
    """A callback for the native layer: None, a tqdm bar (``True``), or the caller's own."""
    if progress is None or progress is False:
        return None, None
    if callable(progress):
        return progress, None
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover - tqdm is optional
        return None, None
    bar = tqdm(total=0, desc=what, unit="")

    def cb(done: int, total: int, message: str) -> None:
        if total and bar.total != total:
            bar.total = total
            bar.refresh()
        bar.set_description(message or what, refresh=False)
        bar.update(max(0, done - bar.n))

    return cb, bar


def _call(progress: Progress, what: str, fn, *args, **kwargs):
    cb, bar = _progress(progress, what)
    try:
        return fn(*args, progress=cb, **kwargs)
    finally:
        if bar is not None:
            bar.close()


def _is_store(p: str) -> bool:
    if p.startswith("s3://"):
        return True
    path = Path(p)
    return path.is_dir() and (path / "zarr.json").exists()


def _cache_dir() -> Path:
    root = os.environ.get("NEUVOLEX_CACHE")
    if root:
        return Path(root)
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "neuvolex"


class Store:
    """A brick store: the volume, its features, models, classifications and labels.

    Open one with :func:`open` or :func:`from_array`.
    """

    def __init__(self, native: "_native.Store", temporary: Optional[str] = None):
        self._native = native
        self.classes: list[int] = []
        """The label of each probability channel of the last :meth:`classify`."""
        self.last_report: Optional[dict] = None
        """The last :meth:`classify`'s report (what ``neuvolex classify --report`` writes)."""
        self._finalizer = (
            weakref.finalize(self, shutil.rmtree, temporary, True) if temporary else None
        )

    # -- geometry ------------------------------------------------------------------------
    @property
    def path(self) -> str:
        """Where the store is (a folder or ``s3://`` URL)."""
        return self._native.path

    @property
    def shape(self) -> tuple[int, int, int]:
        """Voxels along (z, y, x)."""
        x, y, z = self._native.dims
        return (z, y, x)

    @property
    def spacing(self) -> tuple[float, float, float]:
        """Voxel size along (z, y, x), in the source's units (mm for medical images)."""
        x, y, z = self._native.spacing
        return (z, y, x)

    @property
    def affine(self) -> np.ndarray:
        """The NIfTI voxel (x, y, z, 1) to world matrix, 4x4 (nibabel's ``img.affine``)."""
        return np.array(self._native.affine, dtype=np.float64)

    @property
    def napari_affine(self) -> np.ndarray:
        """The voxel-to-world map for napari's (z, y, x) axes: pass as a layer's ``affine``.

        World axes come in the same reversed order (world z, y, x), so layers of the same
        scanner space line up.
        """
        a = self.affine
        n = np.eye(4)
        n[:3, :3] = a[2::-1, 2::-1]
        n[:3, 3] = a[2::-1, 3]
        return n

    @property
    def dtype(self) -> str:
        """The source's voxel type (``u8``, ``i16``, ``f32``, ...)."""
        return self._native.dtype

    @property
    def brick(self) -> int:
        """The brick edge in voxels."""
        return self._native.brick

    @property
    def trained(self) -> bool:
        """Whether the store has a trained INR (needed by the ``inr`` and ``paper`` features)."""
        return self._native.trained

    def __repr__(self) -> str:
        return f"neuvolex.Store('{self.path}', shape (z, y, x) {self.shape}, {self.dtype})"

    # -- data ----------------------------------------------------------------------------
    def read(self, progress: Progress = None) -> np.ndarray:
        """The whole volume as float32 ``[z, y, x]`` (scaled values; small volumes only)."""
        flat = _call(progress, "read", self._native.read)
        return flat.reshape(self.shape)

    def train(
        self,
        preset: str = "fast",
        epochs: Optional[float] = None,
        seconds: Optional[float] = None,
        seed: int = 0,
        progress: Progress = None,
    ) -> dict:
        """Trains the INR on the store (CPU): ``preset`` is ``fast``, ``balanced`` or ``paper``;
        ``epochs`` or ``seconds`` override its budget. ``progress``: ``True`` for a tqdm bar,
        or ``callable(done, total, message)``. Returns the training report."""
        return json.loads(
            _call(progress, "train", self._native.train, preset, epochs, seconds, seed)
        )

    def features(self, kind: str = "filters+xyz", max_bytes: int = 256 << 20):
        """Per-voxel features: a float32 ``[z, y, x, channel]`` numpy array when it fits in
        ``max_bytes``, else a lazy :class:`FeatureArray` computing bricks on access."""
        fa = FeatureArray(self, kind)
        if fa.nbytes <= max_bytes:
            return fa[...]
        return fa

    # -- classification --------------------------------------------------------------------
    def classify(
        self,
        scribbles: np.ndarray,
        features: str = "filters+xyz",
        prior: bool = True,
        trees: int = 100,
        seed: int = 0,
        tau: float = 0.5,
        min_split: int = 8,
        class_weight: str = "balanced",
        background: int = 255,
        prior_mass: Optional[float] = None,
        prior_grow: Optional[int] = None,
        probabilities: bool = True,
        stable: Optional[float] = 0.25,
        progress: Progress = None,
    ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Classifies every voxel from scribbles, as ``neuvolex classify`` does (the same
        pipeline, so the same labels for the same settings).

        ``scribbles``: an integer array of the volume's shape ``[z, y, x]``; 0 is unlabelled,
        ``background`` (255) paints background, any other value a class. Returns the labels
        ``[z, y, x]`` (uint8, or uint16 past 255; 0 = background) after the spatial prior, and
        the raw class probabilities float32 ``[channel, z, y, x]`` (``None`` when
        ``probabilities=False``), channel ``k`` being the class ``self.classes[k]``.

        Corrections stick: when these scribbles keep every scribble of this store's previous
        call and add more, with the same settings and features, a voxel farther than the filter
        bank's halo (24 voxels) from the added scribbles keeps the label the previous call
        gave, unless the new probabilities prefer its new label by ``stable`` (0.25; the
        session's rule). ``stable=None`` gives every label as this call alone finds it.
        ``self.last_report["voxels_held"]`` counts the voxels that kept their label (``None``
        when there was no previous call to hold to).
        """
        labels, proba, classes, report = _call(
            progress,
            "classify",
            self._native.classify,
            scribbles,
            features,
            prior,
            trees,
            seed,
            tau,
            min_split,
            class_weight,
            background,
            prior_mass,
            prior_grow,
            probabilities,
            stable,
        )
        self.classes = list(classes)
        self.last_report = json.loads(report)
        labels = labels.reshape(self.shape)
        if proba is not None:
            proba = proba.reshape((len(classes),) + self.shape)
        return labels, proba

    def preview_slice(
        self,
        scribbles: np.ndarray,
        axis: Union[str, int] = "z",
        index: int = 0,
        features: str = "filters+xyz",
        trees: int = 100,
        seed: int = 0,
        tau: float = 0.5,
        min_split: int = 8,
        class_weight: str = "balanced",
        background: int = 255,
    ) -> np.ndarray:
        """The labels of one slice, at once: the forest :meth:`classify` trains for the same
        scribbles and settings, predicted only on slice ``index`` along ``axis`` (``'z'``,
        ``'y'``, ``'x'`` or numpy axis 0, 1, 2), before the spatial prior. Equal to that slice of
        ``classify(..., prior=False)``. Returns a 2-D array shaped like ``volume[index]``,
        ``volume[:, index]`` or ``volume[:, :, index]``."""
        if axis not in _AXES:
            raise ValueError(f"axis {axis!r}: expected 'z', 'y', 'x' or 0, 1, 2")
        if int(index) < 0:
            raise ValueError(f"index {index}: must not be negative")
        flat, (w, h) = self._native.preview_slice(
            scribbles, _AXES[axis], int(index), features, trees, seed, tau, min_split, class_weight, background
        )
        return flat.reshape(h, w)

    def suggest_slice(self, axis: Union[str, int] = "z", visited: Iterable[int] = ()) -> Optional[int]:
        """The slice along ``axis`` (``'z'``, ``'y'``, ``'x'`` or numpy axis 0, 1, 2) where the
        last classification is most doubtful, away from ``visited`` slices; ``None`` before any
        classification."""
        if axis not in _AXES:
            raise ValueError(f"axis {axis!r}: expected 'z', 'y', 'x' or 0, 1, 2")
        s = self._native.suggest_slice(_AXES[axis], [int(v) for v in visited])
        return None if s is None else int(s[0])

    def viewpoints(
        self,
        k: int = 8,
        features: str = "filters+xyz",
        views: int = 1800,
        max_views: int = 6,
        seed: int = 0,
        progress: Progress = None,
    ) -> list[dict]:
        """Recommended viewpoints (k-means on the features, view entropy, greedy selection):
        dicts with ``azimuth``, ``elevation`` (degrees), ``direction``, ``entropy``, ``gain``,
        best first; pass ``view=(v["azimuth"], v["elevation"])`` to :func:`render`."""
        return json.loads(
            _call(progress, "viewpoints", self._native.viewpoints, k, features, views, max_views, seed)
        )

    def export(self, path: PathLike, labels: Optional[np.ndarray] = None, force: bool = False) -> None:
        """Writes ``labels`` (``[z, y, x]`` integers; default: the last classification) as a
        NIfTI file with the store's world geometry (affine, spacing, NIfTI frames)."""
        self._native.export(os.fspath(path), labels, force)

    def add_labels(self, name: str, labels: np.ndarray) -> None:
        """Stores ``labels`` (``[z, y, x]`` integers) as the store's label image ``name``."""
        self._native.write_labels(name, labels)


class FeatureArray:
    """Per-voxel features computed brick by brick on access: ``shape`` is
    ``(z, y, x, channels)``; index it like a numpy array, or ask for one :meth:`brick`."""

    dtype = np.dtype(np.float32)

    def __init__(self, store: Store, kind: str):
        self.store = store
        self.kind = kind
        self.channels = store._native.feature_channels(kind)
        self.shape = store.shape + (self.channels,)
        self.ndim = 4
        self._b = store.brick

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape)) * 4

    def brick(self, index: Sequence[int]) -> np.ndarray:
        """The features of brick ``(bz, by, bx)`` as ``[z, y, x, channel]``."""
        bz, by, bx = (int(i) for i in index)
        flat, (sx, sy, sz) = self.store._native.feature_brick(self.kind, [bx, by, bz])
        return flat.reshape(sz, sy, sx, self.channels)

    def __array__(self, dtype=None, copy=None):
        a = self[...]
        return a if dtype is None else a.astype(dtype)

    def __getitem__(self, key) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        if any(k is Ellipsis for k in key):
            i = next(i for i, k in enumerate(key) if k is Ellipsis)
            key = key[:i] + (slice(None),) * (4 - len(key) + 1) + key[i + 1 :]
        key = key + (slice(None),) * (4 - len(key))
        spatial, rest = [], []
        for ax, k in enumerate(key[:3]):
            n = self.shape[ax]
            if isinstance(k, (int, np.integer)):
                k = int(k) + n if k < 0 else int(k)
                if not 0 <= k < n:
                    raise IndexError(f"index {k} out of range for axis {ax} of size {n}")
                spatial.append((k, k + 1, 1))
                rest.append(0)
            elif isinstance(k, slice):
                spatial.append(k.indices(n))
                rest.append(slice(None))
            else:
                raise TypeError("FeatureArray takes integers and slices")
        if any(s[2] < 1 for s in spatial):
            raise IndexError("FeatureArray takes positive slice steps")
        lo = [s[0] for s in spatial]
        hi = [max(s[0], s[1]) for s in spatial]
        out = np.zeros([max(0, h - l) for l, h in zip(lo, hi)] + [self.channels], np.float32)
        b = self._b
        if out.size:
            for bz in range(lo[0] // b, (hi[0] - 1) // b + 1):
                for by in range(lo[1] // b, (hi[1] - 1) // b + 1):
                    for bx in range(lo[2] // b, (hi[2] - 1) // b + 1):
                        f = self.brick((bz, by, bx))
                        org = (bz * b, by * b, bx * b)
                        src, dst = [], []
                        for ax in range(3):
                            a0 = max(lo[ax], org[ax])
                            a1 = min(hi[ax], org[ax] + f.shape[ax])
                            src.append(slice(a0 - org[ax], a1 - org[ax]))
                            dst.append(slice(a0 - lo[ax], a1 - lo[ax]))
                        out[tuple(dst)] = f[tuple(src)]
        steps = tuple(slice(None, None, s[2]) for s in spatial)
        out = out[steps]
        sel = tuple(0 if r == 0 else slice(None) for r in rest)
        return out[sel + (key[3],)]


def open(source: PathLike, store: Optional[PathLike] = None, brick: int = 64, progress: Progress = None) -> Store:
    """Opens a volume: an existing brick store (a folder or ``s3://`` URL) as it is, or a
    volume file (NIfTI, NRRD, OME-Zarr) ingested on first use into ``store`` (default: a cache
    under ``$NEUVOLEX_CACHE`` or ``~/.cache/neuvolex``, reused while the file is unchanged)."""
    s = os.fspath(source)
    if _is_store(s):
        return Store(_native.Store.open(s))
    p = Path(s)
    if not p.exists():
        raise FileNotFoundError(f"{s}: no such file")
    if store is None:
        st = p.stat()
        key = hashlib.sha256(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}|{brick}".encode()).hexdigest()[:16]
        name = p.name.split(".")[0] or "volume"
        target = _cache_dir() / f"{name}-{key}.zarr"
        if (target / "zarr.json").exists():
            try:
                return Store(_native.Store.open(str(target)))
            except (RuntimeError, ValueError):
                pass  # an interrupted ingest: redo it
        target.parent.mkdir(parents=True, exist_ok=True)
        return Store(_call(progress, "ingest", _native.Store.ingest, s, str(target), brick, True))
    return Store(_call(progress, "ingest", _native.Store.ingest, s, os.fspath(store), brick, False))


def _xyz_affine(spacing, origin, affine) -> tuple[list, list]:
    if affine is not None:
        a = np.asarray(affine, dtype=np.float64)
        if a.shape != (4, 4) or not np.all(np.isfinite(a)):
            raise ValueError(f"affine: expected a finite 4x4 matrix, got shape {a.shape}")
        sp = np.linalg.norm(a[:3, :3], axis=0)
        return sp.tolist(), a.tolist()
    sp = np.asarray(spacing, dtype=np.float64)
    if sp.shape != (3,) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise ValueError(f"spacing {tuple(np.ravel(sp))}: expected three positive numbers (z, y, x)")
    org = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    if org.shape != (3,) or not np.all(np.isfinite(org)):
        raise ValueError(f"origin {origin}: expected three finite numbers (z, y, x)")
    sx, sy, sz = sp[::-1]
    ox, oy, oz = org[::-1]
    a = [[sx, 0, 0, ox], [0, sy, 0, oy], [0, 0, sz, oz], [0, 0, 0, 1]]
    return [sx, sy, sz], a


def from_array(
    array: np.ndarray,
    spacing: Sequence[float] = (1.0, 1.0, 1.0),
    origin: Optional[Sequence[float]] = None,
    affine: Optional[np.ndarray] = None,
    store: Optional[PathLike] = None,
    brick: int = 64,
    progress: Progress = None,
) -> Store:
    """A store from a 3-D numpy array ``[z, y, x]`` (uint8, int8, uint16, int16, uint32, int32,
    float32 or float64), read in place when C-ordered (otherwise copied once, in C order).

    Geometry: ``spacing`` and ``origin`` in (z, y, x) order (napari's ``scale`` and
    ``translate``), or a NIfTI voxel (x, y, z) to world ``affine`` (nibabel's ``img.affine``;
    for nibabel's ``[x, y, z]`` data pass ``data.T``). ``store``: where to write it (default:
    a temporary folder removed with the Store).
    """
    if not isinstance(array, np.ndarray):
        array = np.asarray(array)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8)
    sp, aff = _xyz_affine(spacing, origin, affine)
    temporary = None
    if store is None:
        temporary = tempfile.mkdtemp(prefix="neuvolex-")
        store = os.path.join(temporary, "volume.zarr")
    try:
        native = _call(
            progress, "ingest", _native.Store.from_array, array, sp, aff, os.fspath(store), brick, False
        )
    except BaseException:
        if temporary:
            shutil.rmtree(temporary, True)
        raise
    return Store(native, temporary)


def render(
    store: Store,
    labels: Union[None, str, np.ndarray] = None,
    probabilities: bool = False,
    view: Sequence[float] = (30.0, 20.0),
    size: Union[int, Sequence[int]] = 512,
    tf: Optional[str] = None,
    mode: Optional[str] = None,
) -> np.ndarray:
    """Renders ``store`` to an RGBA image ``(height, width, 4)`` uint8.

    Intensity through a transfer function (``tf``: a JSON file or ``preset:NAME``), or, with
    ``labels`` (an integer array ``[z, y, x]`` or the name of a label image in the store, e.g.
    ``"classified"``) or ``probabilities=True`` (the last classification's), the classes'
    colours. ``view`` is (azimuth, elevation) in degrees.
    """
    if not isinstance(store, Store):
        raise ValueError("store: expected a neuvolex.Store")
    if isinstance(size, (int, np.integer)):
        w = h = int(size)
    else:
        w, h = (int(v) for v in size)
    az, el = (float(v) for v in view)
    name = None
    if isinstance(labels, str):
        name = labels
    elif labels is not None:
        store.add_labels("python", np.asarray(labels))
        name = "python"
    rgba = store._native.render(name, probabilities, az, el, w, h, tf, mode)
    return rgba.reshape(h, w, 4)
