"""The import rules of docs/architecture.md, checked on the source (every module parsed with ast).

- no cycle between the domain packages (a folder under ``dronecap/`` that is one stage or the
  camera type);
- no domain package imports the CLI layer (``dronecap/*.py`` command-line modules and
  ``dronecap/commands/``);
- every module is at most :data:`MAX_MODULE_LINES` lines and every function at most
  :data:`MAX_FUNCTION_LINES` lines.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "dronecap"
PAGE = ROOT / "docs" / "architecture.md"

DOMAINS = frozenset(
    {"camera", "calibration", "capture", "simulator", "sfm", "datasets", "nerf", "gap9",
     "federated"}
)  # fmt: skip
CLI_LAYER = frozenset(
    {"cli", "registry", "settings", "settings_cli", "pipeline", "pipeline_spec", "figures",
     "report_html", "commands", "pictures", "workspace"}
)  # fmt: skip
BASES = frozenset(
    {"plots", "files", "errors", "progress", "cpu", "limits"}
)  # shared by every layer
# The "may use" column of docs/architecture.md's package table: domain -> the domains it may
# import. Keep the two in step.
MAY_USE: dict[str, frozenset[str]] = {
    "camera": frozenset(),
    "calibration": frozenset({"camera", "capture"}),
    "capture": frozenset({"camera", "datasets"}),  # writes frames.h5 in the one format
    "simulator": frozenset({"camera"}),
    "datasets": frozenset({"camera"}),
    "sfm": frozenset({"camera", "capture", "datasets"}),
    "nerf": frozenset({"camera", "datasets"}),
    "gap9": frozenset({"nerf"}),
    "federated": frozenset({"nerf", "datasets", "gap9"}),
}
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 80

# Loops between domains that another branch is removing; the lead empties this after merging.
KNOWN_LOOPS: frozenset[frozenset[str]] = frozenset()

# Modules and functions over the limits in folders other helpers own while issue 31 is worked
# on in parallel; the lead empties these after merging their branches.
ALLOWED_LONG_MODULES: frozenset[str] = frozenset()
ALLOWED_LONG_FUNCTIONS: frozenset[str] = frozenset()  # "path/to/module.py:function"


def modules() -> list[Path]:
    """Every Python module of the package."""
    return sorted(PACKAGE.rglob("*.py"))


def module_name(path: Path) -> str:
    """``dronecap/sfm/align.py`` -> ``dronecap.sfm.align`` (a package is its ``__init__``)."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported(path: Path) -> set[str]:
    """The dronecap modules ``path`` imports (top level or inside functions), absolute names."""
    tree = ast.parse(path.read_text(), str(path))
    here = module_name(path).split(".")
    if path.name != "__init__.py":
        here = here[:-1]  # the package holding the module
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = here[: len(here) - node.level + 1]
                base = ".".join(up + ([base] if base else []))
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}  # `from dronecap import plots`
    return {m for m in out if m == "dronecap" or m.startswith("dronecap.")}


def top(name: str) -> str | None:
    """The first folder/module below ``dronecap`` of a module name (None for the package)."""
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else None


def package_graph() -> dict[str, set[str]]:
    """Domain -> the other domains it imports."""
    graph: dict[str, set[str]] = {d: set() for d in DOMAINS}
    for path in modules():
        src = top(module_name(path))
        if src in DOMAINS:
            graph[src] |= {t for m in imported(path) if (t := top(m)) in DOMAINS and t != src}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle():
    """The check below could fail: a three-package ring is found, a chain is not."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_no_loop_between_domain_packages():
    graph = package_graph()
    for a, b in KNOWN_LOOPS:  # cut the known loop's two edges, so any other loop still shows
        graph[a].discard(b)
        graph[b].discard(a)
    assert cycles(graph) == [], f"import loop between packages; graph: {graph}"


def test_each_domain_uses_only_what_the_table_allows():
    graph = package_graph()
    known = {(a, b) for pair in KNOWN_LOOPS for a in pair for b in pair if a != b}
    extra = {(a, b) for a, uses in graph.items() for b in uses - MAY_USE[a] if (a, b) not in known}
    assert extra == set(), "imports the package table of docs/architecture.md does not allow"


def imports_from(sources: frozenset[str], targets: frozenset[str]) -> list[str]:
    """ "module imports name" for every import of a ``targets`` module by a ``sources`` one."""
    return [
        f"{path.relative_to(ROOT)} imports {m}"
        for path in modules()
        if top(module_name(path)) in sources
        for m in imported(path)
        if top(m) in targets
    ]


def test_no_domain_imports_the_cli_layer():
    assert imports_from(DOMAINS, CLI_LAYER) == []


def test_the_shared_bases_import_no_domain_nor_the_cli():
    assert imports_from(BASES, DOMAINS | CLI_LAYER) == []


def test_every_module_is_short():
    long = {
        str(p.relative_to(ROOT)): n
        for p in modules()
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert {k: n for k, n in long.items() if k not in ALLOWED_LONG_MODULES} == {}
    stale = ALLOWED_LONG_MODULES - set(long)
    assert not stale, f"no longer over {MAX_MODULE_LINES} lines, remove from the list: {stale}"


def long_functions() -> dict[str, int]:
    """ "path:function" -> lines, for every function (or method) over the limit."""
    out = {}
    for path in modules():
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                first = min([node.lineno] + [d.lineno for d in node.decorator_list])
                n = node.end_lineno - first + 1
                if n > MAX_FUNCTION_LINES:
                    out[f"{path.relative_to(ROOT)}:{node.name}"] = n
    return out


def test_every_function_is_short():
    long = long_functions()
    assert {k: n for k, n in long.items() if k not in ALLOWED_LONG_FUNCTIONS} == {}
    stale = ALLOWED_LONG_FUNCTIONS - set(long)
    assert not stale, f"no longer over {MAX_FUNCTION_LINES} lines, remove from the list: {stale}"


def page_may_use() -> dict[str, frozenset[str]]:
    """The "may use" column of docs/architecture.md's package table: domain -> domains (the
    first word of each item, ``—`` for none)."""
    table: dict[str, frozenset[str]] = {}
    for line in PAGE.read_text().splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        folder = re.fullmatch(r"`dronecap/(\w+)/`", cells[0]) if len(cells) == 3 else None
        if folder and folder.group(1) in DOMAINS:
            items = [] if cells[2] == "—" else cells[2].split(", ")
            table[folder.group(1)] = frozenset(item.split()[0] for item in items)
    return table


def test_the_page_states_what_the_test_enforces():
    """docs/architecture.md's table is MAY_USE, and every ``dronecap/...`` path it names exists."""
    assert page_may_use() == MAY_USE
    named = set(re.findall(r"`(dronecap/[\w/.]+)", PAGE.read_text()))
    missing = sorted(p for p in named if not (ROOT / p.split(":")[0]).exists())
    assert not missing, f"docs/architecture.md names paths that do not exist: {missing}"
