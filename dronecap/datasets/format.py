"""dronecap's HDF5 dataset format: its layout, and the one import of what reads, writes and
validates it.

Every stage exchanges data through these files (``frames.h5``, ``posed.h5``, ``dataset.h5``,
``shards/client_K.h5``). Layout of a file (all optional parts may be absent):

    /images        uint8   [N, H, W, C]  C = 1 (gray) or 3 (RGB); one chunk per image, lzf
    /alpha         uint8   [N, H, W]     coverage, 255 = opaque
    /poses         float64 [N, 4, 4]     camera-to-world, OpenCV axes (x right, y down, z fwd)
    /names         str     [N]           source name of each frame (file name or "frame_000123")
    /source_index  int64   [N]           index of the frame in its source (video frame number)
    /timestamps    float64 [N]           seconds from the start of the source
    /split         int8    [N]           0 train, 1 val, 2 test, -1 unassigned
    /near_far      float64 [N, 2]        per-view near/far along the optical axis (scene units)
    /shards/<name> int16   [N]           client of each frame under a named sharding (-1: none)
    /camera_index  int16   [N]           index into attrs `cameras` of every frame (version 3)
    /drone         int16   [N]           the drone (source position 0..D-1) of every frame
    /extra/<name>  any     [...]         stage-specific tables (e.g. ingest's per-frame scores)
    attrs: format="dronecap", format_version, kind, intrinsics (fx, fy, cx, cy),
           distortion model + params, aabb [2, 3], normalization [4, 4], background,
           provenance (JSON: stage, params, input hashes, created),
           cameras (JSON list of Camera dicts, version 3), drone_names (JSON list, version 3)

A camera per frame (format_version 3): ``cameras`` is the table of cameras (one per drone, or
per imported camera) and ``camera_index`` points every frame at its own; ``intrinsics`` is the
camera when the file has exactly one (then equal to ``cameras[0]``) and None when there are
several, so single-camera code keeps working. ``drone`` gives every frame's drone (the
position of its source) and ``drone_names`` a name per drone; ``source_index`` is the frame's
index in its own drone's source. A single flight is a swarm of one: files without these fields
(all of version 1 and 2) read as one camera and drone 0 (:meth:`Dataset.camera_of`,
:meth:`Dataset.drones`).

Intrinsics (:class:`dronecap.camera.Camera`: fx, fy, cx, cy plus a lens-distortion model) are in
pixels of the stored resolution, pixel centres at integer + 0.5
(OpenCV convention: the centre of the top-left pixel is (0.5, 0.5) in continuous coordinates,
so a pixel (u, v) index maps to the ray through (u + 0.5, v + 0.5)).

Integrity (format_version 2, what :func:`write_dataset` writes): every array carries HDF5's
Fletcher-32 checksum filter, the file's metadata (superblock, object headers, attributes) is in
the HDF5 1.10 layout whose blocks carry checksums, and strings are fixed-length (stored inside
the checksummed blocks, not in HDF5's unchecked global heap). A flipped byte anywhere that
matters is therefore a read error, never a different image or pose. Version 1 files (no
checksums) are still read.

A file whose superblock is not the checksummed one (version 1 files, foreign HDF5 files) is
first read in a forked child process (:mod:`dronecap.datasets.probe`): damage that makes HDF5 crash
the process (a segfault) or loop forever becomes a one-line :class:`DatasetError` instead. What
no reader can detect without checksums: a flipped bit in an image, a pose or any other stored
number that leaves the value valid (finite, rigid, in range) reads back as a different dataset.

Validation (:meth:`Dataset.validate`, run on every write and every read; the checks are in
:mod:`dronecap.datasets.checks`) checks the schema,
dtypes and shapes, finite values, rigid camera rotations, the camera (``Camera.problems``), an
AABB with max > min that some camera sees, 0 <= near < far, a background in [0, 1]. Every
failure is a :class:`DatasetError`: one line naming the file, the field and the problem.

Where it is done: the in-memory :class:`Dataset` and :class:`DatasetError` in
:mod:`dronecap.datasets.dataset`, the header and the versions read in
:mod:`dronecap.datasets.header`, the camera table's attributes in
:mod:`dronecap.datasets.camera_attrs`, :func:`open_dataset` in :mod:`dronecap.datasets.read` and
:func:`write_dataset` in :mod:`dronecap.datasets.write`. Callers import them from here.
"""

from dronecap.datasets.checks import KINDS, SPLITS
from dronecap.datasets.dataset import Dataset, DatasetError, Intrinsics, provenance
from dronecap.datasets.header import FORMAT, FORMAT_VERSION, READ_VERSIONS, read_header
from dronecap.datasets.read import open_dataset
from dronecap.datasets.write import write_dataset

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "KINDS",
    "READ_VERSIONS",
    "SPLITS",
    "Dataset",
    "DatasetError",
    "Intrinsics",
    "open_dataset",
    "provenance",
    "read_header",
    "write_dataset",
]
