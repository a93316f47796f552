"""Install size: the venv a user gets from ``pip install dronecap`` and from each extra.

Run: ``nice .venv/bin/python benchmarks/install_size.py [--variants core,sim,federated,all]
[--keep DIR]``. Builds a wheel of the committed tree once (``--rev``, default HEAD;
``--pyproject FILE`` tries a dependency change before committing it), then for each variant
creates a fresh venv and installs the wheel with that extra exactly as a user would (``pip
install 'dronecap-*.whl[EXTRA]'``: pip's own configuration decides where torch comes from, and
pip compiles the bytecode as a normal install does). Prints a table and writes it to
``benchmarks/results/install_size.md``:

- the size of each venv (``du``-style: allocated blocks, hard links once, MiB = 2**20 bytes),
  its bytecode (``__pycache__``) and the size without it;
- the biggest distributions of the core, with the part of each that is test code or test data
  shipped inside the package, and which installed distributions require it (why it is there);
- what each extra adds over the core;
- any top-level module installed by two distributions (two OpenCV wheels overwrite each other).

A few minutes per variant on the 2-core machine (the full venv downloads Ray and open3d).
"""

from __future__ import annotations

import argparse
import io
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

from dronecap.files import atomic_output

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results" / "install_size.md"
MIB = 2**20
FLOOR_GB = 1.5  # issue 17: a core install takes <= 1.5 GB (read both as GiB and as 10^9 B)
EXTRA_OF = {"core": "", "sim": "sim", "federated": "federated", "all": "all", "dev": "dev"}
TEST_DIRS = {"test", "tests"}  # folders of test code or data shipped inside a package


@dataclass
class Dist:
    """One installed distribution: sizes in MiB of the files its RECORD lists."""

    name: str
    version: str
    mib: float
    tests_mib: float
    requires: set[str]
    required_by: set[str] = field(default_factory=set)


@dataclass
class Venv:
    """A measured venv: total and bytecode MiB, its distributions by normalised name."""

    name: str
    mib: float
    bytecode_mib: float
    dists: dict[str, Dist]
    shared_modules: dict[str, list[str]]


def norm(name: str) -> str:
    """PEP 503 normalised distribution name (``Foo_Bar`` -> ``foo-bar``)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def allocated(path: Path, seen: set[tuple[int, int]]) -> int:
    """Bytes allocated to ``path`` (a file), 0 for a hard link already counted in ``seen``."""
    st = path.lstat()
    key = (st.st_dev, st.st_ino)
    if key in seen:
        return 0
    seen.add(key)
    return st.st_blocks * 512


def tree_mib(root: Path) -> tuple[float, float]:
    """(all, bytecode) MiB allocated under ``root``, as ``du -sm`` counts (links once)."""
    seen: set[tuple[int, int]] = set()
    total = code = 0
    for p in root.rglob("*"):
        n = allocated(p, seen)
        total += n
        if "__pycache__" in p.parts:
            code += n
    return total / MIB, code / MIB


def requirement_names(dist: metadata.Distribution) -> set[str]:
    """Normalised names of what ``dist`` requires without an extra of its own."""
    names = set()
    for req in dist.requires or []:
        if re.search(r"\bextra\s*==", req):
            continue
        m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
        if m:
            names.add(norm(m.group(1)))
    return names


def site_packages(venv: Path) -> Path:
    """The venv's site-packages folder."""
    return next((venv / "lib").glob("python3*/site-packages"))


def measure(name: str, venv: Path) -> Venv:
    """Sizes of ``venv`` and of each distribution in it (files of its RECORD, bytecode incl.)."""
    site = site_packages(venv)
    dists: dict[str, Dist] = {}
    owners: dict[str, set[str]] = {}
    seen: set[tuple[int, int]] = set()
    for d in metadata.distributions(path=[str(site)]):
        key = norm(d.metadata["Name"])
        size = tests = 0
        for f in d.files or []:
            p = site / f
            if not p.is_file():
                continue
            n = allocated(p, seen)
            size += n
            parts = Path(f).parts
            if TEST_DIRS & set(parts[:-1]) or parts[-1].startswith("test_"):
                tests += n
            if len(parts) > 1 and not parts[0].endswith((".dist-info", ".data", ".libs", "..")):
                owners.setdefault(parts[0], set()).add(key)  # a package folder
        dists[key] = Dist(
            d.metadata["Name"], d.version, size / MIB, tests / MIB, requirement_names(d)
        )
    for key, d in dists.items():
        for r in d.requires:
            if r in dists:
                dists[r].required_by.add(dists[key].name)
    total, code = tree_mib(venv)
    shared = {
        m: sorted(o) for m, o in owners.items() if len(o) > 1 and m not in ("__pycache__", "bin")
    }
    return Venv(name, total, code, dists, shared)


def snapshot(rev: str, dest: Path, pyproject: Path | None) -> Path:
    """The committed tree ``rev`` (links kept) extracted under ``dest``; ``pyproject`` replaces
    its pyproject.toml (to measure a dependency change before committing it)."""
    tar = subprocess.run(["git", "archive", rev], cwd=REPO, check=True, capture_output=True)
    with tarfile.open(fileobj=io.BytesIO(tar.stdout)) as t:
        t.extractall(dest, filter="data")
    if pyproject:
        shutil.copy(pyproject, dest / "pyproject.toml")
    return dest


def run(cmd: list[str]) -> None:
    """Run a command at low priority; one line with its last output if it fails."""
    p = subprocess.run(["nice", *cmd], capture_output=True, text=True)
    if p.returncode:
        tail = (p.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"install_size: {' '.join(cmd[:4])} ... failed: {tail}")


def install(venv: Path, wheel: Path, extra: str) -> None:
    """A fresh venv at ``venv`` with ``wheel[extra]`` installed; checks ``dronecap --help``."""
    if venv.exists():
        shutil.rmtree(venv)
    run([sys.executable, "-m", "venv", str(venv)])
    spec = f"{wheel}[{extra}]" if extra else str(wheel)
    run([str(venv / "bin" / "python"), "-m", "pip", "install", "-q", spec])
    run([str(venv / "bin" / "dronecap"), "--help"])


def table(rows: list[list[str]], head: list[str]) -> list[str]:
    """A markdown table."""
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return out + ["| " + " | ".join(r) + " |" for r in rows]


def verdicts(mib: float) -> str:
    """Whether ``mib`` (MiB) meets the floor read as GiB and as GB of 10^9 bytes."""
    floors = {"GiB": FLOOR_GB * 1024, "GB of 10^9 bytes": FLOOR_GB * 1e9 / MIB}
    return "; ".join(
        f"as {FLOOR_GB} {unit} ({floor:.1f} MiB): **{'met' if mib <= floor else 'NOT met'}** "
        f"({mib - floor:+.0f} MiB)"
        for unit, floor in floors.items()
    )


def report(venvs: list[Venv], top: int, command: str) -> str:
    """The markdown page."""
    core = next((v for v in venvs if v.name == "core"), venvs[0])
    torch = core.dists.get("torch")
    lines = [
        "# Install size: core and extras",
        "",
        f"Command: `{command}`. One fresh venv per install (Python {sys.version.split()[0]}, "
        f"pip's bytecode compilation on, as a normal install); torch "
        f"{torch.version if torch else 'absent'} from what pip's configuration offers. "
        "MiB = 2^20 bytes, allocated blocks as `du -sm` counts them.",
        "",
    ]
    rows = []
    for v in venvs:
        adds = "" if v is core else f"{v.mib - core.mib:+.0f}"
        rows.append(
            [v.name, f"{v.mib:.0f}", f"{v.bytecode_mib:.0f}", f"{v.mib - v.bytecode_mib:.0f}", adds]
        )
    lines += table(rows, ["install", "venv MiB", "bytecode MiB", "without bytecode", "vs core"])
    plain = core.mib - core.bytecode_mib
    lines += [
        "",
        f"Core: {core.mib:.0f} MiB = {core.mib * MIB / 1e9:.2f} GB = {core.mib / 1024:.2f} GiB. "
        f"Floor ≤ {FLOOR_GB} GB {verdicts(core.mib)}. Without bytecode ({plain:.0f} MiB, "
        f"`pip install --no-compile`): {verdicts(plain)}. "
        f"Test code and data shipped inside the core's packages: "
        f"{sum(d.tests_mib for d in core.dists.values()):.0f} MiB.",
        "",
        f"## The {top} biggest distributions of the core",
        "",
    ]
    big = sorted(core.dists.values(), key=lambda d: -d.mib)[:top]
    rows = [
        [d.name, d.version, f"{d.mib:.1f}", f"{d.tests_mib:.1f}", ", ".join(sorted(d.required_by))]
        for d in big
    ]
    lines += table(rows, ["distribution", "version", "MiB", "of which tests", "required by"])
    for v in venvs:
        if v is core:
            continue
        added = sorted((d for k, d in v.dists.items() if k not in core.dists), key=lambda d: -d.mib)
        lines += [
            "",
            f"## `[{v.name}]` adds {len(added)} distributions, "
            f"{sum(d.mib for d in added):.0f} MiB (the biggest)",
            "",
        ]
        rows = [
            [d.name, d.version, f"{d.mib:.1f}", ", ".join(sorted(d.required_by))] for d in added
        ]
        lines += table(rows[:top], ["distribution", "version", "MiB", "required by"])
    lines += ["", "## Top-level modules installed by two distributions", ""]
    shared = [
        f"- {v.name}: `{m}` from {', '.join(o)}" for v in venvs for m, o in v.shared_modules.items()
    ]
    lines += shared or ["none"]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Build, install, measure, print and write the page."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--variants", default="core,sim,federated,all",
        help=f"comma-separated, of {', '.join(EXTRA_OF)} (default core,sim,federated,all)",
    )  # fmt: skip
    ap.add_argument("--rev", default="HEAD", help="the commit to install (default HEAD)")
    ap.add_argument("--pyproject", type=Path, help="use this pyproject.toml instead of rev's")
    ap.add_argument("--keep", type=Path, help="make the venvs in this folder and keep them")
    ap.add_argument("--top", type=int, default=15, help="distributions listed per table")
    ap.add_argument("--out", type=Path, default=OUT, help=f"page to write (default {OUT})")
    args = ap.parse_args()
    names = args.variants.split(",")
    unknown = [n for n in names if n not in EXTRA_OF]
    if unknown:
        raise SystemExit(f"install_size: unknown variant {unknown[0]!r} (one of {list(EXTRA_OF)})")
    with tempfile.TemporaryDirectory(prefix="install_size-") as tmp:
        where = args.keep or Path(tmp)
        src = snapshot(args.rev, Path(tmp) / "src", args.pyproject)
        run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", tmp, str(src)])
        wheel = next(Path(tmp).glob("dronecap-*.whl"))
        venvs = []
        for name in names:
            print(f"installing {name} ...", flush=True)
            install(where / name, wheel, EXTRA_OF[name])
            venvs.append(measure(name, where / name))
    page = report(
        venvs,
        args.top,
        "nice .venv/bin/python benchmarks/install_size.py " + " ".join(sys.argv[1:]),
    )
    print(page)
    with atomic_output(args.out) as tmp_out:
        tmp_out.write_text(page)


if __name__ == "__main__":
    main()
