"""Type stubs of the native module (PyO3). Flat arrays are x fastest: reshape to [z, y, x]."""

from typing import Any, Callable, Optional, Sequence

import numpy as np
import numpy.typing as npt

__version__: str

ProgressCallback = Optional[Callable[[int, int, str], Any]]

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
        progress: ProgressCallback = None,
    ) -> tuple[np.ndarray, Optional[npt.NDArray[np.float32]], list[int], str]: ...
    def preview_slice(
        self,
        scribbles: np.ndarray,
        axis: str,
        index: int,
        features: str = "filters+xyz",
        trees: int = 100,
        seed: int = 0,
        tau: float = 0.5,
        min_split: int = 8,
        class_weight: str = "balanced",
        background: int = 255,
    ) -> tuple[npt.NDArray[np.uint16], list[int]]: ...
    def suggest_slice(self, axis: str = "z", visited: Sequence[int] = ...) -> Optional[tuple[int, float]]: ...
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
    ) -> npt.NDArray[np.uint8]: ...
