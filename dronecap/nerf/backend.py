"""The one door to the C++/OpenMP kernels: building, caching, and the fallback rule.

The hash grid (``csrc/hashgrid.cpp``), the ray marcher (``csrc/march.cpp``) and the field's
fused MLPs (``csrc/mlp.cpp``) are compiled
on first use with ``torch.utils.cpp_extension`` and cached on disk under
``$XDG_CACHE_HOME/dronecap/torch_extensions/<name>-<key>`` (``~/.cache`` by default), where
the key hashes the torch version, the Python version, where torch and the source are installed,
the kernel's C++ source (and the headers in csrc/) and the CPU's instruction-set flags (builds
use ``-march=native``): two
installs or checkouts on one machine, or a shared home on two CPUs, never load or rebuild each
other's build.

Fallback rule (:func:`kernel`), the same for every kernel: backend ``"torch"`` or
``"compile"`` -> the PyTorch reference; ``"cpp"`` -> the kernel or an error; ``"auto"`` -> the
kernel when it builds, else the PyTorch reference with one notice on stderr per process.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import TextIO

from dronecap.cpu import cpu_flags
from dronecap.errors import InputError

BACKENDS = ("auto", "cpp", "compile", "torch")
CSRC = Path(__file__).parent / "csrc"
# kernel name -> (C++ source in csrc/, extra compiler flags)
KERNELS: dict[str, tuple[str, tuple[str, ...]]] = {
    "hashgrid": ("hashgrid.cpp", ()),
    # no fused multiply-add: the float32 results match the reference's tensor arithmetic
    "march": ("march.cpp", ("-ffp-contract=off",)),
    "mlp": ("mlp.cpp", ()),
    # torch's Adam in torch's order of operations; sqrt without errno, so that it vectorises
    "adam": ("adam.cpp", ("-ffp-contract=off", "-fno-math-errno")),
}
FALLBACK_NOTICE = (
    "dronecap: no working C++ compiler ({err}); using the PyTorch reference kernels, "
    "~8x slower (install g++ to get the fast path)"
)
BUILD_NOTICE = "dronecap: building C++ kernels (once, ~80 s)"
WAIT_NOTICE = "dronecap: waiting for another dronecap process building the C++ kernels"
# DRONECAP_NO_SIMD=1 builds the kernels without their AVX2/AVX-512 paths (a separate cached
# build): the scalar baseline benchmarks/train_speed.py compares the SIMD paths with.
NO_SIMD_ENV = "DRONECAP_NO_SIMD"

_loaded: dict[str, object] = {}
_said: set[str] = set()


def _say_once(message: str) -> None:
    """Print ``message`` on stderr the first time it comes up in this process."""
    if message not in _said:
        _said.add(message)
        print(message, file=sys.stderr, flush=True)


def _flags(name: str) -> tuple[str, ...]:
    """Extra compiler flags of kernel ``name`` in this process (KERNELS + :data:`NO_SIMD_ENV`)."""
    extra = ("-DDRONECAP_NO_SIMD",) if os.environ.get(NO_SIMD_ENV) == "1" else ()
    return KERNELS[name][1] + extra


def cache_key(name: str) -> str:
    """12 hex digits naming a build of kernel ``name``: sha256 of the torch version, Python
    version, the install's torch and source paths, the kernel's C++ source, the csrc/ headers,
    its flags, and the CPU flags."""
    import torch

    source, flags = KERNELS[name][0], _flags(name)
    h = hashlib.sha256()
    # the install's own paths too: torch writes them (torch headers, the source file) into the
    # build commands, so two checkouts sharing a cache folder would rebuild each other's
    where = (str(Path(torch.__file__).resolve().parent), str((CSRC / source).resolve()))
    for part in (torch.__version__, sys.version, *where, " ".join(flags), cpu_flags()):
        h.update(part.encode() + b"\0")
    for path in (CSRC / source, *sorted(CSRC.glob("*.h"))):
        h.update(path.read_bytes())
    return h.hexdigest()[:12]


def build_dir(name: str) -> Path:
    """Where kernel ``name`` is built and cached (see the module docstring)."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "dronecap" / "torch_extensions" / f"{name}-{cache_key(name)}"


def load(name: str):
    """The compiled kernel module ``name`` (built on first use, then cached on disk).

    Raises whatever the compiler or loader raises when the kernel cannot be built.
    """
    if name not in _loaded:
        from torch.utils import cpp_extension

        source, flags = KERNELS[name][0], _flags(name)
        folder = build_dir(name)
        folder.mkdir(parents=True, exist_ok=True)
        # torch marks a build in progress with a plain `lock` file and waits forever for it to
        # go away; a build killed mid-way leaves it behind and every later process hangs. Our
        # flock is released by the OS when its holder dies, so while we hold it no other
        # dronecap process is building and any `lock` file is stale.
        with open(folder / ".dronecap-build.lock", "a+") as guard:
            _take_build_lock(guard)
            (folder / "lock").unlink(missing_ok=True)
            if not (folder / f"dronecap_{name}.so").exists():
                _say_once(BUILD_NOTICE)
            _loaded[name] = cpp_extension.load(
                name=f"dronecap_{name}",
                sources=[str((CSRC / source).resolve())],  # the path the cache key hashes
                extra_cflags=["-O3", "-march=native", "-fopenmp", *flags],
                extra_ldflags=["-fopenmp"],
                build_directory=str(folder),
                verbose=False,
            )
    return _loaded[name]


def _take_build_lock(guard: TextIO) -> None:
    """flock ``guard`` (the build folder's lock file); while another process holds it (building
    the kernels), say once on stderr that this one waits, and for whom."""
    import fcntl

    try:
        fcntl.flock(guard, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        guard.seek(0)
        holder = guard.read().strip() or "?"
        _say_once(f"{WAIT_NOTICE} (pid {holder})")
        fcntl.flock(guard, fcntl.LOCK_EX)
    guard.seek(0)
    guard.truncate()
    guard.write(str(os.getpid()))
    guard.flush()


def check_backend(backend: str) -> None:
    """Raise InputError unless ``backend`` is one of :data:`BACKENDS`."""
    if backend not in BACKENDS:
        raise InputError(f"unknown backend {backend!r}; use one of {', '.join(BACKENDS)}")


def kernel(name: str, backend: str = "auto"):
    """The compiled kernel ``name`` to use under ``backend``, or None for the PyTorch
    reference (the fallback rule of the module docstring).

    Raises:
        InputError: an unknown backend, or ``backend == "cpp"`` and the kernel cannot be built.
    """
    check_backend(backend)
    if backend in ("torch", "compile"):
        return None
    try:
        return load(name)
    except Exception as err:  # a missing compiler or a build failure of any kind
        if backend == "cpp":
            raise InputError(f"the C++ kernel {name!r} cannot be built: {err}") from None
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        _say_once(FALLBACK_NOTICE.format(err=first[:120]))
        return None
