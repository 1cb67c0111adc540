"""Type stubs of the native module (PyO3). Flat arrays are x fastest: reshape to [z, y, x];
probabilities are voxel-major (channels innermost): reshape to [z, y, x, channel]. The
settings of classify and preview_slice are positional here; neuvolex's Python layer gives
them their defaults (``defaults()``)."""

from typing import Any, Callable, Optional, Sequence

import numpy as np
import numpy.typing as npt

__version__: str

ProgressCallback = Optional[Callable[[int, int, str], Any]]
Classified = tuple[np.ndarray, Optional[npt.NDArray[np.float32]], list[int], str]

def defaults() -> dict[str, Any]: ...

class Store:
    """A brick store opened once; every call below may release the GIL."""

    @staticmethod
    def open(path: str) -> Store: ...
    @staticmethod
    def ingest(source: str, store: str, brick: int = 64, force: bool = False, progress: ProgressCallback = None) -> Store: ...
    @staticmethod
    def from_array(
        array: np.ndarray,
        spacing: Sequence[float],
        affine: Sequence[Sequence[float]],
        store: str,
        brick: int = 64,
        force: bool = False,
        progress: ProgressCallback = None,
    ) -> Store: ...
    @staticmethod
    def from_slabs(
        reader: Callable[[int, int], np.ndarray],
        shape: Sequence[int],
        dtype: str,
        spacing: Sequence[float],
        affine: Sequence[Sequence[float]],
        store: str,
        brick: int = 64,
        force: bool = False,
        progress: ProgressCallback = None,
    ) -> Store: ...
    @staticmethod
    def phantom(store: str, size: int = 96, seed: int = 0, brick: int = 32, force: bool = False) -> Store: ...
    @property
    def path(self) -> str: ...
    @property
    def dims(self) -> list[int]: ...
    @property
    def spacing(self) -> list[float]: ...
    @property
    def affine(self) -> list[list[float]]: ...
    @property
    def dtype(self) -> str: ...
    @property
    def brick(self) -> int: ...
    @property
    def grid(self) -> list[int]: ...
    @property
    def range(self) -> tuple[float, float]: ...
    @property
    def trained(self) -> bool: ...
    @property
    def label_names(self) -> list[str]: ...
    def read_labels(self, name: str) -> npt.NDArray[np.uint32]: ...
    def read(self, progress: ProgressCallback = None) -> npt.NDArray[np.float32]: ...
    def train(
        self,
        preset: str = "fast",
        epochs: Optional[float] = None,
        seconds: Optional[float] = None,
        seed: int = 0,
        progress: ProgressCallback = None,
    ) -> str: ...
    def feature_channels(self, features: str) -> int: ...
    def feature_brick(self, features: str, index: Sequence[int]) -> tuple[npt.NDArray[np.float32], list[int]]: ...
    def classify(
        self,
        scribbles: np.ndarray,
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
        probabilities: bool,
        progress: ProgressCallback = None,
    ) -> Classified: ...
    def preview_slice(
        self,
        scribbles: np.ndarray,
        axis: str,
        index: int,
        features: str,
        trees: int,
        seed: int,
        tau: float,
        min_split: int,
        class_weight: str,
        background: int,
    ) -> tuple[npt.NDArray[np.uint16], list[int]]: ...
    def suggest_slice(self, axis: str = "z", visited: Sequence[int] = ()) -> Optional[tuple[int, float]]: ...
    def viewpoints(
        self,
        k: int = 8,
        features: str = "filters+xyz",
        views: int = 1800,
        max_views: int = 6,
        seed: int = 0,
        progress: ProgressCallback = None,
    ) -> str: ...
    def export(self, path: str, labels: Optional[np.ndarray] = None, force: bool = False) -> None: ...
    def write_labels(self, name: str, labels: np.ndarray) -> None: ...
    def render(
        self,
        labels: Optional[str] = None,
        probabilities: bool = False,
        azimuth: float = 30.0,
        elevation: float = 20.0,
        width: int = 512,
        height: int = 512,
        tf: Optional[str] = None,
        mode: Optional[str] = None,
        label_array: Optional[np.ndarray] = None,
    ) -> npt.NDArray[np.uint8]: ...

class Session:
    """Interactive rounds on a store, in memory: the stability rule and kept (f16) features."""

    def __init__(self, store: Store, delta: Optional[float] = None, cache_bytes: int = 1 << 30) -> None: ...
    @property
    def store(self) -> Store: ...
    @property
    def delta(self) -> float: ...
    @property
    def cached_bytes(self) -> int: ...
    def classify(
        self,
        scribbles: np.ndarray,
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
        probabilities: bool,
        progress: ProgressCallback = None,
    ) -> Classified: ...
    def preview_slice(
        self,
        scribbles: np.ndarray,
        axis: str,
        index: int,
        features: str,
        trees: int,
        seed: int,
        tau: float,
        min_split: int,
        class_weight: str,
        background: int,
    ) -> tuple[npt.NDArray[np.uint16], list[int]]: ...
    def suggest_slice(self, axis: str = "z", visited: Sequence[int] = ()) -> Optional[tuple[int, float]]: ...
    def history(
        self,
    ) -> Optional[
        tuple[
            str,
            npt.NDArray[np.uint64],
            npt.NDArray[np.uint32],
            npt.NDArray[np.uint16],
            Optional[tuple[npt.NDArray[np.uint16], npt.NDArray[np.uint16], npt.NDArray[np.uint16]]],
        ]
    ]: ...
    def restore(
        self,
        key: str,
        index: list[int],
        scribbles: list[int],
        labels: list[int],
        verdicts: Optional[tuple[list[int], list[int]]] = None,
        agree: Optional[list[int]] = None,
    ) -> None: ...
    def reset(self) -> None: ...
