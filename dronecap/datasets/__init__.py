"""dronecap.datasets: the HDF5 dataset format, Synthetic 360° import, split, shards, export.

The package exports the format's surface (:mod:`dronecap.datasets.format`): ``Dataset``,
``open_dataset``, ``write_dataset`` and the rest of its ``__all__``.
"""

from dronecap.datasets.format import *  # noqa: F403 - the format's surface, listed once there
from dronecap.datasets.format import __all__ as __all__
