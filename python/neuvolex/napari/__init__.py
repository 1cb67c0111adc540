"""napari plugin of neuvolex: the "neuvolex: scribble classifier" dock widget.

Registered through the npe2 manifest ``neuvolex/napari.yaml`` (entry point group
``napari.manifest``). Importing this subpackage imports napari and Qt.
"""

from ._widget import BACKGROUND, CLASSES, SCRIBBLES, NeuvolexWidget

__all__ = ["BACKGROUND", "CLASSES", "SCRIBBLES", "NeuvolexWidget"]
