"""Seeded fuzz of the HDF5 readers: >= 300 mutations of small posed.h5 / dataset.h5 files.

Each mutation (bit flips, truncation, zeroed blocks, attributes of the wrong type or value,
NaN/Inf, non-rigid poses, wrong dtypes and shapes) goes through ``open_dataset`` and through the
``split``, ``shard`` and ``export-transforms`` commands in this process. The floor: no traceback,
no hang, and every mutation is either harmless (the file reads back exactly as written) or
rejected with one line; a command that exits 0 wrote valid output from unchanged data.
"""

from __future__ import annotations

import json
import shutil
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest

from dronecap.datasets.format import DatasetError, open_dataset
from tests.reliability.conftest import run_cli

SEED = 19
Mutation = Callable[[Path, np.random.Generator], None]


# -- raw byte damage ------------------------------------------------------------------------------
def flip_bits(path: Path, rng: np.random.Generator) -> None:
    """Flip 1 to 3 random bits anywhere in the file."""
    b = bytearray(path.read_bytes())
    for _ in range(int(rng.integers(1, 4))):
        b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
    path.write_bytes(bytes(b))


def truncate(path: Path, rng: np.random.Generator) -> None:
    b = path.read_bytes()
    path.write_bytes(b[: int(rng.integers(0, len(b)))])


def zero_block(path: Path, rng: np.random.Generator) -> None:
    b = bytearray(path.read_bytes())
    at = int(rng.integers(len(b)))
    b[at : at + 64] = bytes(len(b[at : at + 64]))
    path.write_bytes(bytes(b))


# -- semantic damage through h5py (checksums recomputed: only validation can catch these) --------
def set_attr(name: str, values: list) -> Mutation:
    def mutate(path: Path, rng: np.random.Generator) -> None:
        value = values[int(rng.integers(len(values)))]
        with h5py.File(path, "r+") as f:
            if value is None:
                del f.attrs[name]
            else:
                f.attrs[name] = value

    mutate.__name__ = f"attr_{name}"
    return mutate


def intrinsics_json(path: Path, rng: np.random.Generator) -> None:
    """The camera with one field made invalid (wrong type, non-finite, non-positive, missing)."""
    bad: list[tuple[str, object]] = [
        ("fx", "160"), ("fx", float("inf")), ("fx", float("nan")), ("fx", 0), ("fy", -3.0),
        ("cx", float("nan")), ("cy", None), ("width", "12"), ("width", 12.5), ("height", 7),
        ("model", "FISHEYE9"), ("model", 3), ("distortion", [0.1]), ("distortion", "none"),
        ("fx", [1, 2]), ("fx", True), ("extra", 1),
    ]  # fmt: skip
    key, value = bad[int(rng.integers(len(bad)))]
    with h5py.File(path, "r+") as f:
        cam = json.loads(f.attrs["intrinsics"])
        if value is None:
            del cam[key]
        else:
            cam[key] = value
        f.attrs["intrinsics"] = np.bytes_(json.dumps(cam).encode())


def replace_array(name: str, make: Callable[[np.ndarray, np.random.Generator], np.ndarray]):
    def mutate(path: Path, rng: np.random.Generator) -> None:
        with h5py.File(path, "r+") as f:
            old = f[name][()]
            new = make(old, rng)
            del f[name]
            if new.size:
                f.create_dataset(name, data=new, chunks=True, fletcher32=True)
            else:
                f.create_dataset(name, data=new)

    mutate.__name__ = f"array_{name}_{make.__name__}"
    return mutate


def nan_entry(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.astype(np.float64)
    a.flat[int(rng.integers(a.size))] = [np.nan, np.inf, -np.inf][int(rng.integers(3))]
    return a


def scaled_rotation(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    a[int(rng.integers(len(a))), :3, :3] *= rng.uniform(1.01, 2.0)
    return a


def reflected_rotation(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    a[int(rng.integers(len(a))), :3, int(rng.integers(3))] *= -1
    return a


def sheared_rotation(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    i = int(rng.integers(len(a)))
    a[i, :3, 0] += rng.uniform(0.05, 0.5) * a[i, :3, 1]
    return a


def bad_bottom_row(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    a[int(rng.integers(len(a))), 3, int(rng.integers(4))] += 0.5
    return a


def one_row_short(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return a[:-1]


def as_float32_noise(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return a.astype(np.float32) + np.float32(rng.random())


def as_strings(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.array([b"x"] * len(a))


def far_before_near(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    i = int(rng.integers(len(a)))
    a[i] = a[i, ::-1]
    return a


def negative_near(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    a[int(rng.integers(len(a))), 0] = -rng.uniform(0.1, 5)
    return a


def split_value(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    a = a.copy()
    a[int(rng.integers(len(a)))] = int(rng.choice([3, 7, -2, 100]))
    return a


def two_channels(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return np.repeat(a[..., :1], 2, axis=-1)


def flat_images(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return a.reshape(len(a), -1)


def empty(a: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return a[:0]


def drop(name: str) -> Mutation:
    def mutate(path: Path, rng: np.random.Generator) -> None:
        with h5py.File(path, "r+") as f:
            del f[name]

    mutate.__name__ = f"drop_{name}"
    return mutate


def without_checksum(path: Path, rng: np.random.Generator) -> None:
    """An array rewritten with the same values but no Fletcher-32 filter (v2 must have it)."""
    with h5py.File(path, "r+") as f:
        name = ["poses", "images", "split", "near_far"][int(rng.integers(4))]
        if name not in f:
            name = "poses"
        data = f[name][()]
        del f[name]
        f[name] = data


def shards_as_array(path: Path, rng: np.random.Generator) -> None:
    with h5py.File(path, "r+") as f:
        f.create_dataset("shards", data=np.zeros(3))


NUM = [np.nan, np.inf, "x", b"1.5"]
SEMANTIC: list[tuple[str, Mutation]] = [
    ("any", set_attr("format_version", ["x", "1.5", b"1.5", 1.5, -1, 0, 3, 99, True, [1, 2]])),
    ("any", set_attr("format", ["", "other", 5, None, np.bytes_(b"\xff\xfe")])),
    ("any", set_attr("kind", ["", "weird", 3, None, "frames_v2"])),
    ("any", intrinsics_json),
    ("any", set_attr("intrinsics", ["not json", "[1, 2]", "{}", 160.0, '{"fx": 1}'])),
    (
        "any",
        set_attr(
            "aabb",
            [
                np.array([[np.nan, 0, 0], [1, 1, 1]]),
                np.array([[0.0, 0, 0], [np.inf, 1, 1]]),
                np.array([[1.0, 1, 1], [0, 0, 0]]),
                np.zeros((2, 3)),
                np.ones(3),
                np.array([[10.0, 10, 10], [11, 11, 11]]) * 50,
                "box",
            ],
        ),
    ),
    ("any", set_attr("normalization", [np.full((4, 4), np.nan), np.eye(3), "eye"])),
    ("any", set_attr("provenance", ["{", "[1]", "3", 4.0, np.bytes_(b"\xff")])),
    ("any", set_attr("stage_attrs", ["}", '"text"', "null", 5])),
    ("any", replace_array("poses", nan_entry)),
    ("any", replace_array("poses", scaled_rotation)),
    ("any", replace_array("poses", reflected_rotation)),
    ("any", replace_array("poses", sheared_rotation)),
    ("any", replace_array("poses", bad_bottom_row)),
    ("any", replace_array("poses", one_row_short)),
    ("any", replace_array("poses", as_strings)),
    ("any", replace_array("near_far", nan_entry)),
    ("any", replace_array("near_far", far_before_near)),
    ("any", replace_array("near_far", negative_near)),
    ("any", replace_array("near_far", one_row_short)),
    ("any", replace_array("timestamps", nan_entry)),
    ("any", replace_array("timestamps", as_strings)),
    ("any", replace_array("source_index", as_float32_noise)),
    ("any", replace_array("images", as_float32_noise)),
    ("any", replace_array("images", two_channels)),
    ("any", replace_array("images", flat_images)),
    ("any", replace_array("images", one_row_short)),
    ("any", replace_array("names", one_row_short)),
    ("any", drop("images")),
    ("any", without_checksum),
    ("any", shards_as_array),
    ("dataset", replace_array("split", split_value)),
    ("dataset", replace_array("split", as_float32_noise)),
    ("dataset", replace_array("split", one_row_short)),
    ("dataset", replace_array("alpha", as_float32_noise)),
    ("dataset", replace_array("alpha", empty)),
    ("dataset", set_attr("background", [np.nan, np.array([2.0, 0, 0]), -0.5, np.zeros(2), "w"])),
]


def mutations() -> list[tuple[str, str, Mutation]]:
    """(file kind, label, mutation): 330 in all, the random ones seeded."""
    out: list[tuple[str, str, Mutation]] = []
    for kind in ("posed", "dataset"):
        out += [(kind, "flip_bits", flip_bits)] * 90
        out += [(kind, "truncate", truncate)] * 5
        out += [(kind, "zero_block", zero_block)] * 10
        for applies, m in SEMANTIC:
            if applies in ("any", kind):
                out += [(kind, m.__name__, m)] * (2 if applies == "any" else 3)
    return out


def strict_json(path: Path) -> object:
    def refuse(const: str) -> None:
        raise ValueError(f"{const} in {path}")

    return json.loads(path.read_text(), parse_constant=refuse)


def commands(kind: str, src: Path, out: Path) -> list[tuple[str, list[str], Callable[[], None]]]:
    """(command, argv, check of its output when it exits 0) for a file of ``kind``."""

    def split_ok() -> None:
        ds = open_dataset(out / "split.h5")
        assert len(ds.indices("train")) and len(ds.indices("test"))

    def shard_ok() -> None:
        for k in range(2):
            open_dataset(out / "shards" / f"client_{k}.h5")

    def export_ok() -> None:
        meta = strict_json(out / "transforms" / "transforms.json")
        assert np.isfinite(np.array([fr["transform_matrix"] for fr in meta["frames"]])).all()

    cmds = [
        ("split", [str(src), "-o", str(out / "split.h5")], split_ok),
        ("export-transforms", [str(src), "-o", str(out / "transforms")], export_ok),
    ]
    if kind == "dataset":
        shard = [str(src), "-o", str(out / "shards"), "--clients", "2", "--scheme", "iid"]
        cmds.append(("shard", shard, shard_ok))
    return cmds


def test_fuzz_of_the_readers(small_files: dict[str, Path], tmp_path: Path) -> None:
    rng = np.random.default_rng(SEED)
    reference = {k: open_dataset(p) for k, p in small_files.items()}
    cases = mutations()
    assert len(cases) >= 300
    tally: Counter[str] = Counter()
    failures: list[str] = []
    for i, (kind, label, mutate) in enumerate(cases):
        src = tmp_path / f"{kind}.h5"
        shutil.copyfile(small_files[kind], src)
        mutate(src, rng)
        what = f"#{i} {kind} {label}"
        try:
            identical = open_dataset(src).same_as(reference[kind])
        except DatasetError as err:
            identical = None
            if "\n" in str(err) or str(src) not in str(err):
                failures.append(f"{what}: open_dataset message not one line naming the file")
        except Exception as err:  # noqa: BLE001
            failures.append(f"{what}: open_dataset raised {type(err).__name__}: {err}")
            continue
        if identical is False:
            failures.append(f"{what}: read back different data without an error")
        tally["harmless" if identical else "rejected"] += 1
        out = tmp_path / "out"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir()
        for command, argv, output_ok in commands(kind, src, out):
            res = run_cli([command, *argv], timeout_s=30)
            if res.crash is not None:
                failures.append(f"{what}: {command} crashed:\n{res.crash}")
            elif res.code == 0:
                if not identical:
                    failures.append(f"{what}: {command} exited 0 on a damaged file")
                else:
                    output_ok()
            elif not res.one_line_error(command):
                failures.append(f"{what}: {command} exit {res.code}, stderr {res.err!r}")
            tally[f"{command} exit {res.code}"] += 1
    print(dict(tally))
    assert not failures, "\n".join(failures[:20])
    # the seeded run damages the data that matters far more often than it misses it
    assert tally["rejected"] > tally["harmless"]


@pytest.mark.parametrize("kind", ["posed", "dataset"])
def test_every_single_bit_flip_of_the_header_is_detected_or_harmless(
    small_files: dict[str, Path], tmp_path: Path, kind: str
) -> None:
    """Exhaustive over the first 2 KB (superblock, root object header, attributes): each bit
    flip is rejected or reads back identical."""
    reference = open_dataset(small_files[kind])
    raw = small_files[kind].read_bytes()
    p = tmp_path / "m.h5"
    bad = []
    for pos in range(min(2048, len(raw))):
        b = bytearray(raw)
        b[pos] ^= 1 << (pos % 8)
        p.write_bytes(bytes(b))
        try:
            if not open_dataset(p).same_as(reference):
                bad.append(pos)
        except DatasetError:
            pass
    assert not bad, f"silently different after flips at {bad[:10]}"
