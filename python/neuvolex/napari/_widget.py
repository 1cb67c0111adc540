"""The neuvolex dock widget: scribble a Labels layer, get a live classification.

The user picks an Image layer; the widget makes a "neuvolex scribbles" Labels layer over it
(same shape and world transform) with napari's paint tool ready. Every paint stroke restarts a
single-shot QTimer (the debounce); when it fires, a copy of the scribbles goes to a napari
thread worker. Each image gets one ``neuvolex.Session`` (``store.session()``): its rounds hold
to the labels the previous round showed (the stability rule) and reuse the features computed
before. In a 2-D view the worker first predicts the slice on screen
(``Session.preview_slice``: the same forest, one slice, no spatial prior), which goes into that
slice of the "neuvolex classes" Labels layer at once; then ``Session.classify`` labels the
whole volume, and its result replaces the data of the classes layer (and, optionally, one
"neuvolex p(...)" Image layer per class). At most one classification runs at a time:
scribbles that change during a run mark it stale, and one more run follows with the newest
scribbles when it ends.

The store is made from the layer's full world transform (its ``affine`` composed with scale,
translate, rotate and shear), or is the reader's own store while the layer lies where that
store says; a dask- or zarr-backed layer is ingested a slab at a time, never read whole.

Nothing here blocks the GUI thread on neuvolex work (store ingestion, classification,
training, export all run in workers); errors end up in the status line and in napari's
notifications, never as an exception in a Qt slot.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from qtpy.QtCore import QTimer, Signal
from qtpy.QtWidgets import (
    QCheckBox,
    QComboBox,
    QFileDialog,
    QFormLayout,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QSpinBox,
    QVBoxLayout,
    QWidget,
)

import napari
from napari.layers import Image, Labels
from napari.qt.threading import create_worker
from napari.utils import progress
from napari.utils.notifications import show_error

#: Scribble value meaning "background" (it is never a class of the result).
BACKGROUND = 255
SCRIBBLES = "neuvolex scribbles"
CLASSES = "neuvolex classes"
ROLE = "neuvolex_role"  # metadata key on the layers this widget makes
FEATURE_SETS = ("filters+xyz", "filters+xyz+encl", "filters", "local", "intensity", "inr", "paper")
NEEDS_TRAINING = ("inr", "paper")
_STORE_DTYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64")

SCRIBBLE_TIP = (
    "Paint in the 'neuvolex scribbles' layer with napari's brush: label 1, 2, ... are "
    f"classes, label {BACKGROUND} is background. At least two different labels are "
    "needed before a classification runs."
)


def _backend():
    """The neuvolex module (imported late so this file imports without the extension)."""
    import neuvolex

    return neuvolex


@dataclass(eq=False)
class _Session:
    """What the widget keeps for one image layer."""

    image: Image
    scribbles: Labels | None = None
    classes: Labels | None = None
    probs: dict[int, Image] = field(default_factory=dict)
    store: Any = None
    rounds: Any = None  # the neuvolex.Session of this image's interactive rounds
    classified: bool = False
    trained: bool = False
    visited: list[int] = field(default_factory=list)
    result: tuple | None = None  # (labels, probabilities or None, classes, seconds)


def _geometry(layer) -> dict[str, Any]:
    """The keyword arguments that put a new layer exactly over ``layer``."""
    return {
        "scale": tuple(layer.scale),
        "translate": tuple(layer.translate),
        "rotate": np.asarray(layer.rotate),
        "shear": np.asarray(layer.shear),
        "affine": np.asarray(layer.affine.affine_matrix),
    }


def world_affine(layer) -> np.ndarray:
    """The layer's full data-to-world map, 4x4 on napari's (z, y, x): its ``affine`` composed
    with its scale, translate, rotate and shear (what napari draws it with)."""
    from napari.utils.transforms import CompositeAffine

    ndim = layer.ndim
    inner = CompositeAffine(
        scale=layer.scale, translate=layer.translate, rotate=layer.rotate, shear=layer.shear, ndim=ndim
    )
    return np.asarray(layer.affine.affine_matrix, dtype=float) @ np.asarray(inner.affine_matrix, dtype=float)


def _class_name(value: int) -> str:
    return "background" if value in (0, BACKGROUND) else f"class {value}"


def _held_note(rounds) -> str:
    """What the stability rule kept in the session's last round ('' when nothing): voxels
    far from the new strokes that kept the label the previous round showed."""
    report = getattr(rounds, "last_report", None)
    held = report.get("voxels_held") if isinstance(report, dict) else None
    return f"; {held} voxels far from the new strokes kept their label" if held else ""


class NeuvolexWidget(QWidget):
    """neuvolex: scribble classifier (dock widget)."""

    #: Emitted from the worker threads, delivered on the GUI thread: (done, total, message).
    _train_progress = Signal(int, int, str)
    _classify_progress = Signal(int, int, str)
    #: Emitted from the classification worker: (session, axis, index, slice labels, seconds).
    _classify_preview = Signal(object)

    def __init__(self, napari_viewer: napari.Viewer, parent: QWidget | None = None):
        super().__init__(parent)
        self.viewer = napari_viewer
        self._sessions: dict[int, _Session] = {}
        self._worker = None  # the running classification
        self._pending = False  # scribbles changed during the running classification
        self._preview_note = ""  # "Preview of slice …" of the running classification
        self._train_worker = None
        self._train_bar = None
        self._cancel_training = False
        #: classification runs started (a test hook: the debounce should coalesce paints)
        self.run_count = 0
        #: the brick edge of the stores this widget makes (and the depth of the slabs it reads
        #: of a dask- or zarr-backed layer at a time)
        self.brick = 64
        #: (labels, probabilities or None, classes, seconds) of the last classification shown
        self.last_result: tuple[np.ndarray, np.ndarray | None, list[int], float] | None = None

        self.setToolTip(SCRIBBLE_TIP)
        self._build_ui()

        self._debounce = QTimer(self)
        self._debounce.setSingleShot(True)
        self._debounce.setInterval(500)
        self._debounce.timeout.connect(self.classify_now)
        self._train_progress.connect(self._on_train_progress)
        self._classify_progress.connect(self._on_classify_progress)
        self._classify_preview.connect(lambda preview: self._on_preview(*preview))

        self.viewer.layers.events.inserted.connect(self._on_layers_changed)
        self.viewer.layers.events.removed.connect(self._on_layers_changed)
        for layer in self._candidate_images():
            layer.events.name.connect(self._on_image_renamed)
        self._refresh_images()

    # ------------------------------------------------------------------ UI
    def _build_ui(self) -> None:
        self.image_combo = QComboBox()
        self.image_combo.setToolTip("The Image layer to classify (3-D, one channel).")
        self.image_combo.currentIndexChanged.connect(self._on_image_chosen)

        self.features_combo = QComboBox()
        self.features_combo.addItems(FEATURE_SETS)
        self.features_combo.setToolTip(
            "Per-voxel features of the random forest. 'inr' and 'paper' need 'Train INR' first."
        )
        self.features_combo.currentIndexChanged.connect(self._on_settings_changed)

        self.trees_spin = QSpinBox()
        self.trees_spin.setRange(1, 2000)
        self.trees_spin.setValue(100)
        self.trees_spin.setToolTip(
            "Trees in the random forest (100 for live rounds; the CLI's default is "
            f"{_backend().DEFAULTS['trees']})."
        )
        self.trees_spin.valueChanged.connect(self._on_settings_changed)

        self.prior_check = QCheckBox("spatial prior")
        self.prior_check.setChecked(True)
        self.prior_check.setToolTip("Smooth the probabilities with the spatial prior.")
        self.prior_check.toggled.connect(self._on_settings_changed)

        self.live_check = QCheckBox("live update")
        self.live_check.setChecked(True)
        self.live_check.setToolTip("Classify again shortly after each paint stroke.")

        self.probs_check = QCheckBox("probability layers")
        self.probs_check.setChecked(False)
        self.probs_check.setToolTip("Also show one 'neuvolex p(class k)' Image layer per class.")
        self.probs_check.toggled.connect(self._on_probs_toggled)

        self.classify_button = QPushButton("Classify now")
        self.classify_button.clicked.connect(self.classify_now)
        self.train_button = QPushButton("Train INR")
        self.train_button.setToolTip("Train the implicit neural representation ('inr'/'paper' features).")
        self.train_button.clicked.connect(self._on_train_clicked)
        self.suggest_button = QPushButton("Suggest slice")
        self.suggest_button.setToolTip("Go to the z slice the classifier is least sure about.")
        self.suggest_button.setEnabled(False)
        self.suggest_button.clicked.connect(self.suggest_slice)
        self.export_button = QPushButton("Export…")
        self.export_button.setToolTip("Save the classes as NIfTI with the volume's geometry.")
        self.export_button.setEnabled(False)
        self.export_button.clicked.connect(self._on_export_clicked)

        self.status = QLabel("Pick an image layer, then paint.")
        self.status.setWordWrap(True)
        self.status.setToolTip(SCRIBBLE_TIP)

        form = QFormLayout()
        form.addRow("image", self.image_combo)
        form.addRow("features", self.features_combo)
        form.addRow("trees", self.trees_spin)
        checks = QHBoxLayout()
        checks.addWidget(self.prior_check)
        checks.addWidget(self.live_check)
        form.addRow(checks)
        form.addRow(self.probs_check)
        buttons1 = QHBoxLayout()
        buttons1.addWidget(self.classify_button)
        buttons1.addWidget(self.train_button)
        buttons2 = QHBoxLayout()
        buttons2.addWidget(self.suggest_button)
        buttons2.addWidget(self.export_button)
        help_label = QLabel(f"Paint label 1, 2, … for classes, {BACKGROUND} for background.")
        help_label.setWordWrap(True)
        help_label.setToolTip(SCRIBBLE_TIP)

        layout = QVBoxLayout(self)
        layout.addLayout(form)
        layout.addLayout(buttons1)
        layout.addLayout(buttons2)
        layout.addWidget(help_label)
        layout.addWidget(self.status)
        layout.addStretch(1)

    def _set_status(self, text: str) -> None:
        self.status.setText(text)

    def _error(self, what: str, exc: BaseException) -> None:
        message = f"{what}: {type(exc).__name__}: {exc}"
        self._set_status(message)
        try:
            show_error(message)
        except Exception:  # noqa: BLE001  (a notification must never take the widget down)
            pass

    # ------------------------------------------------------------- layers
    def _candidate_images(self) -> list[Image]:
        return [
            layer
            for layer in self.viewer.layers
            if isinstance(layer, Image) and ROLE not in layer.metadata
        ]

    def _refresh_images(self, create: bool = True) -> None:
        """Sync the combo box with the viewer's Image layers; ``create``: make the scribbles
        layer when the chosen image changes (not while layers are being removed)."""
        current = self.image_layer
        images = self._candidate_images()
        self.image_combo.blockSignals(True)
        self.image_combo.clear()
        for layer in images:
            self.image_combo.addItem(layer.name, id(layer))
        if current in images:
            self.image_combo.setCurrentIndex(images.index(current))
        self.image_combo.blockSignals(False)
        if self.image_layer is not current:
            self._on_image_chosen(create=create)

    def _on_layers_changed(self, event=None) -> None:
        layer = getattr(event, "value", None)
        if getattr(event, "type", "") == "removed":
            if layer is not None:
                self._forget_layer(layer)
            self._refresh_images(create=False)  # e.g. the viewer closing: add nothing
            return
        if isinstance(layer, Image) and ROLE not in layer.metadata:
            layer.events.name.connect(self._on_image_renamed)
        # After napari has finished adding (and selecting) the new layer.
        QTimer.singleShot(0, self._refresh_images)

    def _on_image_renamed(self, event=None) -> None:
        for i, layer in enumerate(self._candidate_images()):
            if i < self.image_combo.count():
                self.image_combo.setItemText(i, layer.name)

    def _forget_layer(self, layer) -> None:
        session = self._sessions.pop(id(layer), None)
        if session is not None:  # the image went: its store goes with it
            session.store = session.rounds = None
            return
        for session in self._sessions.values():
            if session.scribbles is layer:
                session.scribbles = None
            elif session.classes is layer:
                session.classes = None
                session.classified = False
            else:
                for value, prob in list(session.probs.items()):
                    if prob is layer:
                        del session.probs[value]
        self._update_buttons()

    def _disconnect_viewer(self, *_):
        for emitter, slot in (
            (self.viewer.layers.events.inserted, self._on_layers_changed),
            (self.viewer.layers.events.removed, self._on_layers_changed),
        ):
            try:
                emitter.disconnect(slot)
            except Exception:  # noqa: BLE001
                pass

    @property
    def image_layer(self) -> Image | None:
        """The Image layer picked in the combo box."""
        key = self.image_combo.currentData()
        for layer in self._candidate_images():
            if id(layer) == key:
                return layer
        return None

    @property
    def session(self) -> _Session | None:
        image = self.image_layer
        if image is None:
            return None
        session = self._sessions.get(id(image))
        if session is None or session.image is not image:
            session = self._sessions[id(image)] = _Session(image)
        return session

    @property
    def scribbles_layer(self) -> Labels | None:
        session = self.session
        return None if session is None else session.scribbles

    @property
    def classes_layer(self) -> Labels | None:
        session = self.session
        return None if session is None else session.classes

    def _on_image_chosen(self, *_, create: bool = True):
        session = self.session
        if session is None:
            self._set_status("Add a 3-D Image layer to start.")
            self._update_buttons()
            return
        problem = self._unsupported(session.image)
        if problem:
            self._set_status(problem)
            self._update_buttons()
            return
        if create:
            self.ensure_scribbles()
        self._update_buttons()

    @staticmethod
    def _unsupported(image: Image) -> str | None:
        if getattr(image, "multiscale", False):
            return f"'{image.name}' is multiscale; neuvolex needs a single 3-D array."
        if getattr(image, "rgb", False):
            return f"'{image.name}' is RGB; neuvolex needs one channel."
        if image.data.ndim != 3:
            return f"'{image.name}' has {image.data.ndim} dimensions; neuvolex needs 3 (z, y, x)."
        return None

    def ensure_scribbles(self) -> Labels | None:
        """The scribbles layer of the chosen image (made, selected, paint tool ready)."""
        session = self.session
        if session is None or self._unsupported(session.image):
            return None
        layer = session.scribbles
        if layer is None or layer not in self.viewer.layers:
            image = session.image
            layer = Labels(
                np.zeros(image.data.shape, dtype=np.uint8),
                name=SCRIBBLES,
                metadata={ROLE: "scribbles", "neuvolex_image": image.name},
                **_geometry(image),
            )
            self._color_background(layer)
            self.viewer.layers.append(layer)
            layer.events.paint.connect(self._on_scribbles_changed)
            layer.events.data.connect(self._on_scribbles_changed)
            session.scribbles = layer
            self._set_status(
                f"Paint into '{layer.name}': label 1, 2, … are classes, {BACKGROUND} is background."
            )
        self.viewer.layers.selection.active = layer
        layer.selected_label = 1
        layer.mode = "paint"
        return layer

    @staticmethod
    def _color_background(layer: Labels) -> None:
        """Label 255 in grey, the others as napari would colour them."""
        try:
            from napari.utils.colormaps import DirectLabelColormap

            values = np.arange(1, BACKGROUND)
            colors = layer.colormap.map(values)
            color_dict = {int(v): c for v, c in zip(values, colors)}
            color_dict[BACKGROUND] = np.array([0.6, 0.6, 0.6, 1.0])
            color_dict[0] = np.zeros(4)
            color_dict[None] = np.zeros(4)
            layer.colormap = DirectLabelColormap(color_dict=color_dict)
        except Exception:  # noqa: BLE001  (cosmetic only)
            pass

    # ------------------------------------------------------- classification
    def _on_scribbles_changed(self, event=None) -> None:
        if self.live_check.isChecked():
            self._debounce.start()  # restarts: a burst of strokes makes one run

    def _on_settings_changed(self, *_):
        session = self.session
        if session is not None and session.classified and self.live_check.isChecked():
            self._debounce.start()

    def classify_now(self) -> bool:
        """Classify the chosen image with its scribbles now (in a worker thread).

        Returns True when a run started or was queued behind the running one.
        """
        self._debounce.stop()
        if self._worker is not None or self._train_worker is not None:
            # One more run with the newest scribbles when the running work ends (a store
            # runs one call at a time).
            self._pending = True
            if self._train_worker is not None:
                self._set_status("Training the INR; the classification follows it.")
            return True
        session = self.session
        if session is None:
            self._set_status("No image layer to classify.")
            return False
        problem = self._unsupported(session.image)
        if problem:
            self._set_status(problem)
            return False
        scribbles = session.scribbles
        if scribbles is None or scribbles not in self.viewer.layers:
            self.ensure_scribbles()
            self._set_status("Paint at least two different labels first.")
            return False
        data = np.array(scribbles.data, copy=True)
        if data.dtype != np.uint8:  # the API wants 0 / 1..254 / 255 in an integer array
            data = data.astype(np.uint16 if data.max(initial=0) > BACKGROUND else np.uint8)
        counts = np.bincount(data.ravel().astype(np.int64, copy=False), minlength=256)
        painted = [int(v) for v in np.flatnonzero(counts[1:]) + 1]
        if len(painted) < 2:
            self._set_status(
                "Paint at least two different labels (e.g. 1 and "
                f"{BACKGROUND} = background); painted so far: {painted or 'none'}."
            )
            return False
        features = self.features_combo.currentText()
        if features in NEEDS_TRAINING and not self._trained(session):
            self._set_status(f"Features '{features}' need 'Train INR' first.")
            return False
        settings = {
            "features": features,
            "prior": self.prior_check.isChecked(),
            "trees": int(self.trees_spin.value()),
            "probabilities": self.probs_check.isChecked(),
        }
        source = self._store_source(session)
        preview = self.displayed_slice(session.image)
        self.run_count += 1
        self._preview_note = ""
        what = "the whole volume"
        if preview is not None:
            what = f"slice {_axis_name(preview[0])} = {preview[1]}, then {what}"
        self._set_status(
            f"Classifying {what} ({features}, {settings['trees']} trees, "
            f"prior {'on' if settings['prior'] else 'off'}) …"
        )
        progress_cb = self._classify_progress.emit

        def preview_cb(*shown, s=session):  # in the worker; the slot runs on the GUI thread
            self._classify_preview.emit((s, *shown))

        worker = create_worker(
            _classify, source, data, settings, progress_cb, preview, preview_cb,
            _ignore_errors=True,
        )
        worker.returned.connect(lambda result, s=session: self._on_classified(s, result))
        worker.errored.connect(lambda exc: self._error("classification failed", exc))
        worker.finished.connect(self._on_classify_finished)
        self._worker = worker
        self.classify_button.setEnabled(False)
        worker.start()
        return True

    def displayed_slice(self, image: Image) -> tuple[int, int] | None:
        """(axis of ``image``'s data, index) of the slice the viewer shows of ``image``.

        ``None`` in a 3-D view, or when the slice plane is not a plane of the data (a rotated
        or sheared layer cuts its voxels obliquely)."""
        dims = self.viewer.dims
        if dims.ndisplay != 2 or image.ndim != 3:
            return None
        offset = dims.ndim - image.ndim  # the layer's axes are the viewer's last ones
        axes = [a - offset for a in dims.not_displayed if a >= offset]
        if len(axes) != 1:
            return None
        (axis,) = axes
        point = np.asarray(dims.point, dtype=float)
        try:
            data = np.asarray(image.world_to_data(point), dtype=float)
            # Along the displayed axes the slice must stay at the same index of `axis`.
            for displayed in dims.displayed:
                moved = point.copy()
                moved[displayed] += 1.0
                shifted = np.asarray(image.world_to_data(moved), dtype=float)
                if not np.isclose(shifted[axis], data[axis], atol=1e-6):
                    return None
        except Exception:  # noqa: BLE001  (no preview, never a broken run)
            return None
        if not np.isfinite(data[axis]):
            return None
        size = image.data.shape[axis]
        index = int(np.clip(np.round(data[axis]), 0, size - 1))  # napari rounds the same way
        return axis, index

    @property
    def busy(self) -> bool:
        """Whether a classification is running or waiting for the debounce timer."""
        return self._worker is not None or self._debounce.isActive() or self._pending

    def _store_source(self, session: _Session) -> Callable[[], Any]:
        """A callable (run in a worker) giving the session's neuvolex Session (its rounds on
        the image's store), made once. The store takes the layer's full world transform
        (affine, scale, translate, rotate, shear); a dask- or zarr-backed layer is ingested a
        slab at a time, never read whole."""
        image = session.image
        affine = world_affine(image)
        neuvolex = _backend()
        if session.store is None:
            meta = image.metadata.get("neuvolex_store")
            # A reader's store serves while the layer still lies where the store says.
            if (
                isinstance(meta, getattr(neuvolex, "Store", ()))
                and tuple(meta.shape) == tuple(image.data.shape)
                and np.allclose(meta.napari_affine, affine, atol=1e-6)
            ):
                session.store = meta
        data = image.data
        brick = int(self.brick)

        def make():
            if session.store is None:
                array = data if hasattr(data, "__getitem__") and hasattr(data, "dtype") else np.asarray(data)
                if np.dtype(array.dtype).name not in _STORE_DTYPES + ("bool",):
                    array = array.astype(np.float32) if hasattr(array, "astype") else np.asarray(array, np.float32)
                session.store = neuvolex.from_array(array, affine=affine, brick=brick)
            if session.rounds is None:
                session.rounds = session.store.session()
            return session.rounds

        return make

    def _on_classify_progress(self, done: int, total: int, message: str) -> None:
        if self._worker is not None:
            what = f" {message}" if message else ""
            note = f"{self._preview_note} " if self._preview_note else ""
            self._set_status(f"{note}Classifying the whole volume:{what} {done}/{total}")

    def _on_preview(self, session: _Session, axis: int, index: int, labels, seconds: float) -> None:
        """The labels of the slice on screen, ahead of the whole volume: into that slice of
        the classes layer (made with zeros if there is none), the view left as it is."""
        if session.image not in self.viewer.layers:  # the image went while it ran
            return
        labels = np.asarray(labels)
        shape = tuple(session.image.data.shape)
        where = [slice(None)] * len(shape)
        where[axis] = index
        where = tuple(where)
        view = self._view()
        layer = session.classes
        if layer is not None and layer in self.viewer.layers:
            data = layer.data
            if not isinstance(data, np.ndarray) or data.shape != shape:
                layer.data = data = np.zeros(shape, dtype=labels.dtype)
            elif labels.size and labels.max() > np.iinfo(data.dtype).max:
                layer.data = data = data.astype(labels.dtype)
            data[where] = labels  # in place, as napari's brush edits a Labels layer
            layer.refresh()
        else:
            data = np.zeros(shape, dtype=labels.dtype)
            data[where] = labels
            self._add_classes_layer(session, data)
        self._restore_view(view)
        self._preview_note = f"Preview of slice {_axis_name(axis)} = {index} in {seconds:.2f} s."
        self._set_status(f"{self._preview_note} Classifying the whole volume …")

    @staticmethod
    def _trained(session: _Session) -> bool:
        return session.trained or bool(getattr(session.store, "trained", False))

    def _on_classified(self, session: _Session, result) -> None:
        if session.image not in self.viewer.layers:  # the image went while it ran
            return
        labels, probs, classes, seconds = result
        self.last_result = session.result = result
        session.classified = True
        view = self._view()
        if session.classes is not None and session.classes in self.viewer.layers:
            session.classes.data = labels
        else:
            self._add_classes_layer(session, labels)
        if self.probs_check.isChecked() and probs is not None:
            self._show_probs(session, probs, classes)
        self._restore_view(view)
        counts = np.bincount(labels.ravel().astype(np.int64, copy=False))
        summary = ", ".join(
            f"{_class_name(c)}: {int(counts[c]) if c < counts.size else 0} voxels"
            for c in classes
            if c not in (0, BACKGROUND)
        )
        self._set_status(
            f"{len(classes)} classes {list(classes)} in {seconds:.1f} s — {summary}"
            f"{_held_note(session.rounds)}"
        )
        self._update_buttons()

    def _view(self) -> tuple:
        """The viewer's current step and active layer, to put back after layers change."""
        return tuple(self.viewer.dims.current_step), self.viewer.layers.selection.active

    def _restore_view(self, view: tuple) -> None:
        step, active = view
        if tuple(self.viewer.dims.current_step) != step:
            self.viewer.dims.current_step = step
        if active is not None and active in self.viewer.layers:
            self.viewer.layers.selection.active = active

    def _add_classes_layer(self, session: _Session, data: np.ndarray) -> None:
        """The "neuvolex classes" layer of ``session``'s image, below its scribbles."""
        layer = Labels(
            data,
            name=CLASSES,
            opacity=0.5,
            metadata={ROLE: "classes", "neuvolex_image": session.image.name},
            **_geometry(session.image),
        )
        self._insert_below_scribbles(session, layer)
        session.classes = layer

    def _insert_below_scribbles(self, session: _Session, layer) -> None:
        layers = self.viewer.layers
        if session.scribbles is not None and session.scribbles in layers:
            layers.insert(layers.index(session.scribbles), layer)
        else:
            layers.append(layer)

    def _show_probs(self, session: _Session, probs: np.ndarray, classes: list[int]) -> None:
        colormaps = ("red", "green", "blue", "magenta", "cyan", "yellow")
        for k, value in enumerate(classes):
            value = int(value)
            layer = session.probs.get(value)
            if layer is not None and layer in self.viewer.layers:
                layer.data = probs[..., k]
                continue
            layer = Image(
                probs[..., k],
                name=f"neuvolex p({_class_name(value)})",
                colormap=colormaps[k % len(colormaps)],
                blending="additive",
                contrast_limits=(0.0, 1.0),
                opacity=0.5,
                visible=value not in (0, BACKGROUND),
                metadata={ROLE: "probability", "neuvolex_class": value},
                **_geometry(session.image),
            )
            self._insert_below_scribbles(session, layer)
            session.probs[value] = layer

    def _on_probs_toggled(self, checked: bool) -> None:
        session = self.session
        if session is None:
            return
        if checked:
            probs = None if session.result is None else session.result[1]
            if probs is not None and session.classified:
                self._show_probs(session, probs, session.result[2])
            elif session.classified:
                self.classify_now()  # the last run did not keep probabilities
        else:
            for layer in list(session.probs.values()):
                if layer in self.viewer.layers:
                    self.viewer.layers.remove(layer)
            session.probs.clear()

    def _on_classify_finished(self) -> None:
        self._worker = None
        self.classify_button.setEnabled(True)
        if self._pending:
            self._pending = False
            self.classify_now()

    def _update_buttons(self) -> None:
        session = self.session
        done = session is not None and session.classified
        self.suggest_button.setEnabled(done)
        self.export_button.setEnabled(done)

    # ------------------------------------------------------------ training
    def _on_train_clicked(self) -> None:
        if self._train_worker is not None:
            self._cancel_training = True
            self.train_button.setText("Cancelling…")
            return
        self.train()

    def train(self, **kwargs) -> bool:
        """Train the INR of the chosen image in a worker; progress in the activity dock."""
        session = self.session
        if session is None or self._unsupported(session.image):
            self._set_status("No 3-D image layer to train on.")
            return False
        if self._worker is not None or self._train_worker is not None:
            self._set_status("Busy: train again when the running work ends.")
            return False
        source = self._store_source(session)
        self._cancel_training = False

        def callback(done: int, total: int, message: str) -> None:
            if self._cancel_training:
                raise KeyboardInterrupt("training cancelled")  # neuvolex stops at the next step
            self._train_progress.emit(int(done), int(total), str(message))

        def run():
            try:
                return source().store.train(progress=callback, **kwargs)
            except KeyboardInterrupt as exc:  # not out of a worker thread: Qt would abort
                raise _Cancelled(str(exc)) from None

        self._train_bar = progress(total=0, desc="neuvolex: training INR")
        worker = create_worker(run, _ignore_errors=True)
        worker.returned.connect(lambda summary, s=session: self._on_trained(s, summary))
        worker.errored.connect(self._on_train_error)
        worker.finished.connect(self._on_train_finished)
        self._train_worker = worker
        self.train_button.setText("Cancel training")
        self._set_status("Training the INR …")
        worker.start()
        return True

    def _on_train_progress(self, done: int, total: int, message: str) -> None:
        bar = self._train_bar
        if bar is None:
            return
        if total and bar.total != total:
            bar.total = total
        if done > bar.n:
            bar.update(done - bar.n)
        if message:
            bar.set_description(f"neuvolex: {message}")
        self._set_status(f"Training: {done}/{total} {message}")

    def _on_trained(self, session: _Session, summary) -> None:
        session.trained = True
        if isinstance(summary, dict):
            scalars = [(k, v) for k, v in summary.items() if isinstance(v, (int, float, str))]
            text = ", ".join(
                f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in scalars[:6]
            )
        else:
            text = str(summary)
        self._set_status(f"INR trained ({text[:300]}). Features 'inr' and 'paper' are available.")

    def _on_train_error(self, exc: BaseException) -> None:
        if isinstance(exc, (_Cancelled, KeyboardInterrupt)) or self._cancel_training:
            self._set_status("Training cancelled.")
        else:
            self._error("training failed", exc)

    def _on_train_finished(self) -> None:
        self._train_worker = None
        self.train_button.setText("Train INR")
        if self._train_bar is not None:
            self._train_bar.close()
            self._train_bar = None
        if self._pending:
            self._pending = False
            self.classify_now()

    # ---------------------------------------------------- suggest / export
    def suggest_slice(self) -> int | None:
        """Go to the most doubtful z slice (not one suggested before); returns it."""
        session = self.session
        if session is None or not session.classified or session.store is None:
            self._set_status("Classify first; then 'Suggest slice' finds the most doubtful slice.")
            return None
        if self._worker is not None or self._train_worker is not None:
            self._set_status("Busy: ask again when the running work ends.")
            return None
        try:
            # The session's last round (its rounds write nothing into the store).
            source = getattr(session.rounds, "suggest_slice", session.store.suggest_slice)
            index = source(axis="z", visited=tuple(session.visited))
        except Exception as exc:  # noqa: BLE001
            self._error("suggest slice failed", exc)
            return None
        if index is None:
            self._set_status("No slice to suggest (no classification, or all slices visited).")
            return None
        index = int(index)
        session.visited.append(index)
        # The image's z axis is the first of its three, the last three of the viewer's.
        axis = self.viewer.dims.ndim - session.image.ndim
        world = session.image.data_to_world([index, 0, 0])[0]
        self.viewer.dims.set_point(axis, world)
        self._set_status(f"Most doubtful slice: z = {index}. Paint there, then look again.")
        return index

    def _on_export_clicked(self) -> None:
        path, _ = QFileDialog.getSaveFileName(
            self, "Export neuvolex classes", "classes.nii.gz", "NIfTI (*.nii.gz *.nii)"
        )
        if path:
            self.export(path)

    def export(self, path: str) -> bool:
        """Write the classes (as shown, edits included) as NIfTI with the volume's geometry."""
        session = self.session
        if session is None or not session.classified or session.store is None:
            self._set_status("Nothing to export yet: classify first.")
            return False
        if self._worker is not None or self._train_worker is not None:
            self._set_status("Busy: export when the running work ends.")
            return False
        if not path.endswith((".nii", ".nii.gz")):
            path += ".nii.gz"
        labels = None
        if session.classes is not None and session.classes in self.viewer.layers:
            labels = np.asarray(session.classes.data)
        try:
            # The file dialog has asked about overwriting already.
            session.store.export(os.fspath(path), labels=labels, force=True)
        except Exception as exc:  # noqa: BLE001
            self._error("export failed", exc)
            return False
        self._set_status(f"Exported the classes to {path}.")
        return True

    # -------------------------------------------------------------- closing
    def wait(self, timeout_ms: int = 60000) -> None:
        """Block until the running workers end (for tests and closing)."""
        deadline = time.monotonic() + timeout_ms / 1000
        from qtpy.QtWidgets import QApplication

        while (self._worker is not None or self._train_worker is not None) and time.monotonic() < deadline:
            QApplication.processEvents()
            time.sleep(0.01)

    def closeEvent(self, event) -> None:  # noqa: N802
        self._debounce.stop()
        self._pending = False
        self._cancel_training = True
        self._disconnect_viewer()
        super().closeEvent(event)


class _Cancelled(Exception):
    """A neuvolex call stopped by the user (KeyboardInterrupt must not leave a Qt thread)."""


def _axis_name(axis: int) -> str:
    return "zyx"[axis] if 0 <= axis < 3 else f"axis {axis}"


def _classify(
    source: Callable[[], Any],
    scribbles: np.ndarray,
    settings: dict,
    progress_cb=None,
    preview: tuple[int, int] | None = None,
    preview_cb: Callable[..., None] | None = None,
):
    """Worker body: when ``preview`` names a slice (axis, index), first its labels go to
    ``preview_cb(axis, index, labels, seconds)``; then returns (labels, probabilities or None,
    classes, seconds) of the whole volume.

    (A plain function, not a generator worker: napari's generator workers take a
    RuntimeError for a deleted worker and drop it without an ``errored`` signal.)"""
    rounds = source()
    if preview is not None and preview_cb is not None:
        axis, index = preview
        start = time.perf_counter()
        try:
            labels = rounds.preview_slice(
                scribbles, axis=axis, index=index, features=settings["features"], trees=settings["trees"]
            )
        except KeyboardInterrupt as exc:
            raise _Cancelled(str(exc) or "cancelled") from None
        except ValueError:
            raise  # bad scribbles: the whole volume would fail the same way
        except Exception:  # noqa: BLE001  (a store without previews: the whole volume only)
            labels = None
        if labels is not None:
            preview_cb(axis, index, np.asarray(labels), time.perf_counter() - start)
    start = time.perf_counter()
    try:
        labels, probs = rounds.classify(scribbles, progress=progress_cb, **settings)
    except KeyboardInterrupt as exc:
        raise _Cancelled(str(exc) or "cancelled") from None
    seconds = time.perf_counter() - start
    probs = None if probs is None else np.asarray(probs)
    return np.asarray(labels), probs, [int(c) for c in rounds.classes], seconds
