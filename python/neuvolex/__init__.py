"""neuvolex from Python: out-of-core volume exploration with learned features.

Conventions, the same for every function:

- Arrays are numpy-ordered ``a[z, y, x]`` (napari's order); per-axis tuples (``spacing``,
  ``origin``, ``shape``) follow the same (z, y, x) order, like napari's ``scale`` and
  ``translate``, and so does the ``affine`` :func:`from_array` takes (napari's ``affine``).
- Arrays with channels put them last: features and probabilities are ``[z, y, x, channel]``.
- ``Store.affine`` is the file's NIfTI voxel-to-world matrix, acting on (x, y, z, 1) as
  nibabel's ``img.affine`` does (RAS+ mm); ``Store.napari_affine`` is the same map for
  napari's axes.
- :meth:`Store.classify` is a function of its arguments; interactive rounds that hold to
  their own history go through :meth:`Store.session`. Defaults are the CLI's, from the Rust
  library (:data:`DEFAULTS`).
- Errors derive from :class:`neuvolex.Error` (see :mod:`neuvolex.errors`).

    import neuvolex
    store = neuvolex.open("ct.nii.gz")             # ingested once into a cached brick store
    labels, proba = store.classify(scribbles)      # scribbles: int array [z, y, x], 0 = none
    image = neuvolex.render(store, labels=labels)  # (H, W, 4) uint8

Long calls release the GIL and run on a worker thread; Ctrl-C cancels them at the next brick.
"""

from __future__ import annotations

import builtins
import hashlib
import json
import os
import shutil
import tempfile
import types
import weakref
from pathlib import Path
from typing import Any, Callable, Iterable, Optional, Sequence, Union

import numpy as np

from . import _native
from .errors import (
    ArgumentError,
    Cancelled,
    Error,
    FileError,
    LockError,
    MissingFileError,
    NeuvolexRuntimeError,
)

__all__ = [
    "Store",
    "Session",
    "FeatureArray",
    "DEFAULTS",
    "open",
    "from_array",
    "render",
    "sample_phantom",
    "Error",
    "ArgumentError",
    "FileError",
    "MissingFileError",
    "LockError",
    "Cancelled",
    "NeuvolexRuntimeError",
    "__version__",
]
__version__ = _native.__version__

#: The classification defaults shared with ``neuvolex classify`` and the service, read from
#: the Rust library's own ``Default`` implementations (one place for every front end):
#: ``features``, ``prior``, ``trees``, ``min_split``, ``seed``, ``class_weight``, ``tau``,
#: ``background``, ``prior_mass``, ``prior_grow``, and the stability rule's ``delta`` and
#: ``margin`` (voxels) of :class:`Session`.
DEFAULTS: "types.MappingProxyType[str, Any]" = types.MappingProxyType(dict(_native.defaults()))
_D = DEFAULTS

PathLike = Union[str, "os.PathLike[str]"]
Progress = Union[None, bool, Callable[[int, int, str], Any]]

_AXES = {"z": "z", "y": "y", "x": "x", 0: "z", 1: "y", 2: "x"}
_SESSION_FORMAT = 1


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


def _settings(
    features: str,
    prior: bool,
    trees: int,
    seed: int,
    tau: float,
    min_split: int,
    class_weight: str,
    background: int,
    prior_mass: Optional[float],
    prior_grow: Optional[int],
) -> tuple:
    """The native layer's positional settings, checked for type (values are checked there)."""
    for name, v in (("trees", trees), ("seed", seed), ("min_split", min_split), ("background", background)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
            raise ArgumentError(f"{name} {v!r}: expected a non-negative integer")
    return (
        str(features),
        bool(prior),
        int(trees),
        int(seed),
        float(tau),
        int(min_split),
        str(class_weight),
        int(background),
        None if prior_mass is None else float(prior_mass),
        None if prior_grow is None else int(prior_grow),
    )


def _check_axis(axis, index) -> str:
    if axis not in _AXES:
        raise ArgumentError(f"axis {axis!r}: expected 'z', 'y', 'x' or 0, 1, 2")
    if int(index) < 0:
        raise ArgumentError(f"index {index}: must not be negative")
    return _AXES[axis]


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
        scanner space line up; :func:`from_array` takes an affine in this convention.
        """
        return _napari_from_nifti(self.affine)

    @property
    def dtype(self) -> np.dtype:
        """The source's voxel type, a :class:`numpy.dtype`."""
        return np.dtype(self._native.dtype)

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

    def features(self, kind: str = _D["features"]) -> "FeatureArray":
        """Per-voxel features ``[z, y, x, channel]`` float32, always as a lazy
        :class:`FeatureArray` that computes bricks on access: ``np.asarray(f)`` gives them all,
        ``f[10:20]`` a part, ``f.to_dask()`` (or ``dask.array.from_array(f)``) a dask array."""
        return FeatureArray(self, kind)

    # -- classification --------------------------------------------------------------------
    def classify(
        self,
        scribbles: np.ndarray,
        features: str = _D["features"],
        prior: bool = _D["prior"],
        trees: int = _D["trees"],
        seed: int = _D["seed"],
        tau: float = _D["tau"],
        min_split: int = _D["min_split"],
        class_weight: str = _D["class_weight"],
        background: int = _D["background"],
        prior_mass: Optional[float] = None,
        prior_grow: Optional[int] = None,
        probabilities: bool = True,
        progress: Progress = None,
    ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """Classifies every voxel from scribbles, as ``neuvolex classify`` does (the same
        pipeline and the same defaults, :data:`DEFAULTS`, so the same labels for the same
        settings). The result depends on the arguments only, never on earlier calls; for
        rounds that hold to their own history use :meth:`session`.

        ``scribbles``: an integer array of the volume's shape ``[z, y, x]``; 0 is unlabelled,
        ``background`` (255) paints background, any other value a class. ``prior_mass`` and
        ``prior_grow`` default to the prior's own (``DEFAULTS``). Returns the labels
        ``[z, y, x]`` (uint8, or uint16 past 255; 0 = background) after the spatial prior, and
        the raw class probabilities float32 ``[z, y, x, channel]`` (``None`` when
        ``probabilities=False``), channel ``k`` being the class ``self.classes[k]``. The run is
        also kept in the store as its last classification (what :meth:`suggest_slice`,
        :meth:`export` and ``render(probabilities=True)`` read).
        """
        args = _settings(features, prior, trees, seed, tau, min_split, class_weight, background, prior_mass, prior_grow)
        out = _call(progress, "classify", self._native.classify, scribbles, *args, bool(probabilities))
        return self._unpack(out)

    def _unpack(self, out) -> tuple[np.ndarray, Optional[np.ndarray]]:
        labels, proba, classes, report = out
        self.classes = [int(c) for c in classes]
        self.last_report = json.loads(report)
        labels = labels.reshape(self.shape)
        if proba is not None:
            proba = proba.reshape(self.shape + (len(classes),))
        return labels, proba

    def session(self, delta: Optional[float] = None, cache_bytes: int = 1 << 30) -> "Session":
        """A :class:`Session` of interactive rounds on this store (what the napari widget
        uses): ``delta`` is the stability rule's (default ``DEFAULTS["delta"]``), and at most
        ``cache_bytes`` of computed features are kept for the next rounds."""
        return Session(self, delta=delta, cache_bytes=cache_bytes)

    def preview_slice(
        self,
        scribbles: np.ndarray,
        axis: Union[str, int] = "z",
        index: int = 0,
        features: str = _D["features"],
        trees: int = _D["trees"],
        seed: int = _D["seed"],
        tau: float = _D["tau"],
        min_split: int = _D["min_split"],
        class_weight: str = _D["class_weight"],
        background: int = _D["background"],
    ) -> np.ndarray:
        """The labels of one slice, at once: the forest :meth:`classify` trains for the same
        scribbles and settings, predicted only on slice ``index`` along ``axis`` (``'z'``,
        ``'y'``, ``'x'`` or numpy axis 0, 1, 2), before the spatial prior. Equal to that slice of
        ``classify(..., prior=False)``. Returns a 2-D array shaped like ``volume[index]``,
        ``volume[:, index]`` or ``volume[:, :, index]``."""
        a = _check_axis(axis, index)
        args = _settings(features, False, trees, seed, tau, min_split, class_weight, background, None, None)
        flat, (w, h) = self._native.preview_slice(
            scribbles, a, int(index), args[0], args[2], args[3], args[4], args[5], args[6], args[7]
        )
        return flat.reshape(h, w)

    def suggest_slice(self, axis: Union[str, int] = "z", visited: Iterable[int] = ()) -> Optional[int]:
        """The slice along ``axis`` (``'z'``, ``'y'``, ``'x'`` or numpy axis 0, 1, 2) where the
        store's last classification is most doubtful, away from ``visited`` slices; ``None``
        before any classification."""
        a = _check_axis(axis, 0)
        s = self._native.suggest_slice(a, [int(v) for v in visited])
        return None if s is None else int(s[0])

    def viewpoints(
        self,
        k: int = 8,
        features: str = _D["features"],
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
        """Writes ``labels`` (``[z, y, x]`` integers; default: the store's last classification)
        as a NIfTI file with the store's world geometry (affine, spacing, NIfTI frames)."""
        self._native.export(os.fspath(path), labels, force)

    def add_labels(self, name: str, labels: np.ndarray) -> None:
        """Saves ``labels`` (``[z, y, x]`` integers) in the store as its label image ``name``
        (then ``render(store, labels=name)`` draws it). Nothing else writes label images."""
        self._native.write_labels(name, labels)


class Session:
    """Interactive rounds on one store, as the browser's session and the napari widget run
    them: each :meth:`classify` holds to the labels this session's previous round gave
    (the stability rule of ``neuvolex_classify::stable``: beyond ``DEFAULTS["margin"]`` voxels
    of the strokes added since, a voxel keeps its label unless the new probabilities prefer
    the change by ``delta``), and the features it computed are kept for the next rounds (in
    half precision, as the browser's service keeps them), so a round after the first costs the
    forest and the prediction only. Rounds run in memory and write nothing into the store:
    :meth:`suggest_slice` reads the session's last round, and :meth:`Store.add_labels` or
    :meth:`Store.export` with ``labels=`` save its labels.

    Made by :meth:`Store.session`; saved with :meth:`save` and restored with :meth:`load`.
    Only this object's own rounds count: :meth:`Store.classify` never holds to anything.
    """

    def __init__(self, store: Store, delta: Optional[float] = None, cache_bytes: int = 1 << 30):
        if not isinstance(store, Store):
            raise ArgumentError("store: expected a neuvolex.Store")
        if delta is not None and not 0.0 <= float(delta) <= 1.0:
            raise ArgumentError(f"delta {delta}: must be between 0 and 1")
        self.store = store
        """The store the rounds classify."""
        self._native = _native.Session(store._native, None if delta is None else float(delta), int(cache_bytes))
        self.classes: list[int] = []
        """The label of each probability channel of the last round."""
        self.last_report: Optional[dict] = None
        """The last round's report; ``voxels_held`` counts the voxels that kept their label
        (``None`` when there was nothing to hold to)."""

    @property
    def delta(self) -> float:
        """The stability rule's ``delta``."""
        return float(self._native.delta)

    @property
    def cached_bytes(self) -> int:
        """Bytes of feature bricks kept for the next rounds."""
        return int(self._native.cached_bytes)

    def __repr__(self) -> str:
        return f"neuvolex.Session({self.store!r}, delta {self.delta}, {self.cached_bytes} feature bytes kept)"

    def classify(
        self,
        scribbles: np.ndarray,
        features: str = _D["features"],
        prior: bool = _D["prior"],
        trees: int = _D["trees"],
        seed: int = _D["seed"],
        tau: float = _D["tau"],
        min_split: int = _D["min_split"],
        class_weight: str = _D["class_weight"],
        background: int = _D["background"],
        prior_mass: Optional[float] = None,
        prior_grow: Optional[int] = None,
        probabilities: bool = True,
        progress: Progress = None,
    ) -> tuple[np.ndarray, Optional[np.ndarray]]:
        """One round: :meth:`Store.classify` with the same arguments and result types, on the
        kept features rounded to half precision (float16) and with the probabilities in steps
        of 1/255 (the values ``Store.classify`` returns too); so a label may differ from
        ``Store.classify``'s where rounding a feature moves it across a split. When these
        scribbles keep every scribble of this session's previous round and add more, with the
        same settings and model, the labels beyond the margin of the added strokes hold to
        that round's (``self.last_report["voxels_held"]`` counts them). Nothing is written into
        the store (unlike :meth:`Store.classify`)."""
        args = _settings(features, prior, trees, seed, tau, min_split, class_weight, background, prior_mass, prior_grow)
        out = _call(progress, "classify", self._native.classify, scribbles, *args, bool(probabilities))
        labels, proba = self.store._unpack(out)
        self.classes = list(self.store.classes)
        self.last_report = self.store.last_report
        return labels, proba

    def preview_slice(
        self,
        scribbles: np.ndarray,
        axis: Union[str, int] = "z",
        index: int = 0,
        features: str = _D["features"],
        trees: int = _D["trees"],
        seed: int = _D["seed"],
        tau: float = _D["tau"],
        min_split: int = _D["min_split"],
        class_weight: str = _D["class_weight"],
        background: int = _D["background"],
    ) -> np.ndarray:
        """:meth:`Store.preview_slice` through the session's kept features (the stroked slice
        first, before a whole round)."""
        a = _check_axis(axis, index)
        args = _settings(features, False, trees, seed, tau, min_split, class_weight, background, None, None)
        flat, (w, h) = self._native.preview_slice(
            scribbles, a, int(index), args[0], args[2], args[3], args[4], args[5], args[6], args[7]
        )
        return flat.reshape(h, w)

    def suggest_slice(self, axis: Union[str, int] = "z", visited: Iterable[int] = ()) -> Optional[int]:
        """:meth:`Store.suggest_slice` under this session's last round: the slice along
        ``axis`` where its probabilities are most doubtful, away from ``visited`` slices;
        ``None`` before any round."""
        a = _check_axis(axis, 0)
        s = self._native.suggest_slice(a, [int(v) for v in visited])
        return None if s is None else int(s[0])

    def reset(self) -> None:
        """Forgets the last round: the next one holds to nothing (the kept features stay)."""
        self._native.reset()

    def save(self, path: PathLike) -> None:
        """Writes the session's state (its store's location, the rule's ``delta`` and the last
        round: settings, scribbles, labels and the round's own decisions the rule holds) to
        ``path``, a ``.npz`` file."""
        h = self._native.history()
        state: dict[str, Any] = {
            "format": np.int64(_SESSION_FORMAT),
            "store": np.str_(self.store.path),
            "delta": np.float64(self.delta),
            "shape": np.asarray(self.store.shape, np.int64),
            "classes": np.asarray(self.classes, np.int64),
        }
        if h is not None:
            key, index, scribbled, labels, verdicts = h
            state.update(key=np.str_(key), index=index, scribbles=scribbled, labels=labels)
            if verdicts is not None:
                state.update(forest=verdicts[0], verdict=verdicts[1])
                if len(verdicts[2]):
                    state.update(agree=verdicts[2])
        with builtins.open(os.fspath(path), "wb") as f:
            np.savez_compressed(f, **state)

    @classmethod
    def load(cls, path: PathLike, store: Optional[Store] = None, cache_bytes: int = 1 << 30) -> "Session":
        """A session restored from :meth:`save`'s file: its next round holds to the saved
        round. ``store``: the store to use (default: the saved store's location, opened)."""
        p = os.fspath(path)
        if not os.path.exists(p):
            raise MissingFileError(f"{p}: no such session file")
        try:
            with np.load(p, allow_pickle=False) as z:
                state = {k: z[k] for k in z.files}
        except (OSError, ValueError) as e:
            raise FileError(f"{p}: not a neuvolex session file ({e})") from None
        if int(state.get("format", -1)) != _SESSION_FORMAT:
            raise FileError(f"{p}: not a neuvolex session file (format {state.get('format')})")
        if store is None:
            store = open(str(state["store"]))
        if tuple(int(v) for v in state["shape"]) != store.shape:
            raise FileError(f"{p}: saved for a volume of shape {tuple(state['shape'])}, the store is {store.shape}")
        s = cls(store, delta=float(state["delta"]), cache_bytes=cache_bytes)
        if "key" in state:
            verdicts, agree = None, None
            if "forest" in state and "verdict" in state:
                verdicts = (state["forest"].astype(np.uint16).tolist(), state["verdict"].astype(np.uint16).tolist())
                if "agree" in state:
                    agree = state["agree"].astype(np.uint16).tolist()
            try:
                s._native.restore(
                    str(state["key"]),
                    state["index"].astype(np.uint64).tolist(),
                    state["scribbles"].astype(np.uint32).tolist(),
                    state["labels"].astype(np.uint16).tolist(),
                    verdicts,
                    agree,
                )
            except FileError as e:
                raise FileError(f"{p}: {e}") from None
            s.classes = [int(c) for c in state["classes"]]
        return s


class FeatureArray:
    """Per-voxel features computed brick by brick on access: ``shape`` is
    ``(z, y, x, channels)``, float32. Index it like a numpy array, convert it with
    ``np.asarray`` (NumPy 2's ``copy=False`` is refused, as it must be: nothing is stored to
    share), ask for one :meth:`brick`, or get a dask array of bricks with :meth:`to_dask`."""

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
        """Bytes of the whole array once computed."""
        return int(np.prod(self.shape)) * 4

    @property
    def size(self) -> int:
        """Elements of the whole array."""
        return int(np.prod(self.shape))

    def __len__(self) -> int:
        return self.shape[0]

    def __repr__(self) -> str:
        return f"neuvolex.FeatureArray('{self.kind}', shape (z, y, x, channel) {self.shape})"

    def brick(self, index: Sequence[int]) -> np.ndarray:
        """The features of brick ``(bz, by, bx)`` as ``[z, y, x, channel]``."""
        bz, by, bx = (int(i) for i in index)
        flat, (sx, sy, sz) = self.store._native.feature_brick(self.kind, [bx, by, bz])
        return flat.reshape(sz, sy, sx, self.channels)

    def to_dask(self):
        """A dask array over the same features, one chunk per brick."""
        import dask.array as da

        b = self._b
        return da.from_array(self, chunks=(b, b, b, self.channels), asarray=False, fancy=False)

    def __array__(self, dtype=None, copy=None):
        if copy is False:
            raise ValueError("FeatureArray: features are computed on access; a copy is always made (copy=False refused)")
        a = self[...]
        return a if dtype is None else a.astype(dtype, copy=False)

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
        try:
            return Store(_native.Store.open(s))
        except (FileError, NeuvolexRuntimeError):
            if s.startswith("s3://"):
                raise
            # A Zarr folder that is not a brick store (an OME-Zarr image): ingested below.
    p = Path(s)
    if not p.exists():
        raise MissingFileError(f"{s}: no such file")
    if store is None:
        st = p.stat()
        key = hashlib.sha256(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}|{brick}".encode()).hexdigest()[:16]
        name = p.name.split(".")[0] or "volume"
        target = _cache_dir() / f"{name}-{key}.zarr"
        if (target / "zarr.json").exists():
            try:
                return Store(_native.Store.open(str(target)))
            except Error:
                pass  # an interrupted ingest: redo it
        target.parent.mkdir(parents=True, exist_ok=True)
        return Store(_call(progress, "ingest", _native.Store.ingest, s, str(target), brick, True))
    return Store(_call(progress, "ingest", _native.Store.ingest, s, os.fspath(store), brick, False))


def _napari_from_nifti(a: np.ndarray) -> np.ndarray:
    """A NIfTI voxel (x, y, z) to world (x, y, z) matrix as napari's (z, y, x) to (z, y, x)."""
    n = np.eye(4)
    n[:3, :3] = a[2::-1, 2::-1]
    n[:3, 3] = a[2::-1, 3]
    return n


def _nifti_from_napari(n: np.ndarray) -> np.ndarray:
    """The inverse of :func:`_napari_from_nifti` (the same reversal)."""
    return _napari_from_nifti(n)


def _geometry(spacing, origin, affine) -> tuple[list, list]:
    """The native layer's spacing and NIfTI affine (both x, y, z) from (z, y, x) arguments."""
    if affine is not None:
        a = np.asarray(affine, dtype=np.float64)
        if a.shape != (4, 4) or not np.all(np.isfinite(a)):
            raise ArgumentError(f"affine: expected a finite 4x4 matrix, got shape {a.shape}")
        if not np.allclose(a[3], [0, 0, 0, 1]):
            raise ArgumentError(f"affine: the last row must be [0, 0, 0, 1], got {a[3].tolist()}")
        sp = np.linalg.norm(a[:3, :3], axis=0)  # per voxel axis (z, y, x)
        if spacing is not None:
            given = np.asarray(spacing, dtype=np.float64)
            if given.shape != (3,) or not np.allclose(given, sp, rtol=1e-6, atol=1e-9):
                raise ArgumentError(
                    f"spacing {tuple(np.ravel(given))} conflicts with the affine, whose columns "
                    f"give voxel sizes (z, y, x) {tuple(np.round(sp, 9))}: pass one or the other"
                )
        if origin is not None:
            given = np.asarray(origin, dtype=np.float64)
            if given.shape != (3,) or not np.allclose(given, a[:3, 3], rtol=1e-6, atol=1e-9):
                raise ArgumentError(
                    f"origin {tuple(np.ravel(given))} conflicts with the affine's translation "
                    f"(z, y, x) {tuple(a[:3, 3])}: pass one or the other"
                )
        nifti = _nifti_from_napari(a)
        return np.linalg.norm(nifti[:3, :3], axis=0).tolist(), nifti.tolist()
    sp = np.asarray((1.0, 1.0, 1.0) if spacing is None else spacing, dtype=np.float64)
    if sp.shape != (3,) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise ArgumentError(f"spacing {tuple(np.ravel(sp))}: expected three positive numbers (z, y, x)")
    org = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    if org.shape != (3,) or not np.all(np.isfinite(org)):
        raise ArgumentError(f"origin {origin}: expected three finite numbers (z, y, x)")
    sx, sy, sz = sp[::-1]
    ox, oy, oz = org[::-1]
    a = [[sx, 0, 0, ox], [0, sy, 0, oy], [0, 0, sz, oz], [0, 0, 0, 1]]
    return [sx, sy, sz], a


def from_array(
    array,
    spacing: Optional[Sequence[float]] = None,
    origin: Optional[Sequence[float]] = None,
    affine: Optional[np.ndarray] = None,
    store: Optional[PathLike] = None,
    brick: int = 64,
    progress: Progress = None,
) -> Store:
    """A store from a 3-D array ``[z, y, x]`` (uint8, int8, uint16, int16, uint32, int32,
    float32 or float64; bool as uint8). A numpy array is read in place when C-ordered; any
    other array that slices like numpy (dask, zarr, h5py, memory-mapped) is read a slab of
    z-slices at a time, never whole, so it may be larger than memory.

    Geometry, in (z, y, x) order throughout: ``spacing`` and ``origin`` (napari's ``scale`` and
    ``translate``; default 1 and 0), or ``affine``, the 4x4 voxel (z, y, x) to world (z, y, x)
    matrix napari's ``affine`` takes (what :attr:`Store.napari_affine` returns). Spacing or
    origin that disagree with a given affine are refused. For nibabel's ``img.affine`` and
    ``[x, y, z]`` data, prefer :func:`open` on the file. ``store``: where to write it
    (default: a temporary folder removed with the Store).
    """
    sp, aff = _geometry(spacing, origin, affine)
    lazy = not isinstance(array, np.ndarray) and hasattr(array, "shape") and hasattr(array, "dtype") and hasattr(array, "__getitem__")
    if not lazy:
        array = np.asarray(array)
        if array.dtype == np.bool_:
            array = array.astype(np.uint8)
    elif len(array.shape) != 3:
        raise ArgumentError(f"array: expected a 3-D array [z, y, x], got {len(array.shape)} dimensions")
    temporary = None
    if store is None:
        temporary = tempfile.mkdtemp(prefix="neuvolex-")
        store = os.path.join(temporary, "volume.zarr")
    try:
        if lazy:
            dtype = np.dtype(array.dtype)
            target = np.dtype(np.uint8) if dtype == np.bool_ else dtype

            def reader(z0: int, depth: int) -> np.ndarray:
                return np.ascontiguousarray(np.asarray(array[z0 : z0 + depth]), dtype=target)

            native = _call(
                progress, "ingest", _native.Store.from_slabs, reader, [int(n) for n in array.shape],
                target.name, sp, aff, os.fspath(store), brick, False,
            )
        else:
            native = _call(progress, "ingest", _native.Store.from_array, array, sp, aff, os.fspath(store), brick, False)
    except BaseException:
        if temporary:
            shutil.rmtree(temporary, True)
        raise
    return Store(native, temporary)


def sample_phantom(size: int = 96, seed: int = 0, store: Optional[PathLike] = None) -> tuple[Store, np.ndarray]:
    """The generated phantom (an abdomen-like CT, ``size`` voxels wide, i16 HU) and its ground
    truth labels ``[z, y, x]`` (uint8): napari's sample data, and a small volume to try the
    classifier on. ``store``: where to write it (default: a temporary folder)."""
    temporary = None
    if store is None:
        temporary = tempfile.mkdtemp(prefix="neuvolex-phantom-")
        store = os.path.join(temporary, "phantom.zarr")
    try:
        s = Store(_native.Store.phantom(os.fspath(store), int(size), int(seed)), temporary)
    except BaseException:
        if temporary:
            shutil.rmtree(temporary, True)
        raise
    labels = s._native.read_labels("ground_truth").reshape(s.shape)
    return s, labels.astype(np.uint8 if labels.max(initial=0) <= 255 else np.uint16)


def render(
    store: Store,
    labels: Union[None, str, np.ndarray] = None,
    probabilities: bool = False,
    view: Sequence[float] = (30.0, 20.0),
    size: Union[int, Sequence[int]] = 512,
    tf: Optional[str] = None,
    mode: Optional[str] = None,
) -> np.ndarray:
    """Renders ``store`` to an RGBA image ``(height, width, 4)`` uint8; nothing is written.

    Intensity through a transfer function (``tf``: a JSON file or ``preset:NAME``), or, with
    ``labels`` (an integer array ``[z, y, x]``, drawn from memory, or the name of a label image
    in the store, e.g. ``"classified"``) or ``probabilities=True`` (the store's last
    classification's), the classes' colours. ``view`` is (azimuth, elevation) in degrees.
    """
    if not isinstance(store, Store):
        raise ArgumentError("store: expected a neuvolex.Store")
    if isinstance(size, (int, np.integer)):
        w = h = int(size)
    else:
        w, h = (int(v) for v in size)
    az, el = (float(v) for v in view)
    name, array = (labels, None) if isinstance(labels, str) or labels is None else (None, np.asarray(labels))
    rgba = store._native.render(name, probabilities, az, el, w, h, tf, mode, array)
    return rgba.reshape(h, w, 4)
