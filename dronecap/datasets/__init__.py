"""dronecap.datasets: the HDF5 dataset format, Synthetic 360° import, split, shards, export."""

from dronecap.datasets.format import (
    FORMAT,
    FORMAT_VERSION,
    SPLITS,
    Dataset,
    DatasetError,
    Intrinsics,
    open_dataset,
    provenance,
    read_header,
    write_dataset,
)

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "SPLITS",
    "Dataset",
    "DatasetError",
    "Intrinsics",
    "open_dataset",
    "provenance",
    "read_header",
    "write_dataset",
]
