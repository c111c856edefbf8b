"""The package's shape: stages import only earlier stages, functions fit on a screen, portable process code.

The import graph is read from the source (every ``import`` statement, module level or inside a
function, outside ``if TYPE_CHECKING:`` blocks), so a lazy import cannot hide a dependency.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

from conftest import LONGEST_FIRST, run_each_in_a_fresh_process

PACKAGE = Path(__file__).resolve().parents[1] / "carvi_torch"

#: The stages in the order data flows through them; a module of a stage may import modules of its
#: own stage (the order inside a stage is checked for cycles below) and of earlier stages only.
STAGES = [
    ("viewpoints", ["viewpoints.bundle", "viewpoints.camera_fit", "viewpoints.sfm", "viewpoints.mixture",
                    "viewpoints.refine", "viewpoints"]),
    ("surrogates", ["surrogates"]),
    ("carve", ["carve.geometry", "carve.grids", "carve.torch_backend", "carve.native", "carve.reference",
               "carve.dispatch", "carve"]),
    ("select", ["select"]),
    ("mesh", ["mesh", "marching"]),
    ("write", ["io.write_worker", "io.writer", "io.results"]),
]
#: Imports of a later stage that the public contract asks for, with the reason.
ALLOWED = {("carve.grids", "mesh"): "VoxelGrid.to_mesh() is part of the public API"}


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(path: Path) -> set[str]:
    """The package modules ``path`` imports (relative names resolved, TYPE_CHECKING blocks skipped)."""
    me = _module_name(path).split(".") if _module_name(path) else []
    is_pkg = path.name == "__init__.py"
    out: set[str] = set()

    def visit(node):
        if isinstance(node, ast.If) and _is_type_checking(node):
            for child in node.orelse:
                visit(child)
            return
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = me if is_pkg else me[:-1]
                base = base[:len(base) - (node.level - 1)] if node.level > 1 else base
                mod = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.startswith("carvi_torch"):
                mod = node.module[len("carvi_torch"):].lstrip(".")
            else:
                mod = None
            if mod is not None:
                for alias in node.names:
                    sub = f"{mod}.{alias.name}" if mod else alias.name
                    out.add(sub if (PACKAGE / Path(*sub.split("."))).with_suffix(".py").is_file()
                            or (PACKAGE / Path(*sub.split(".")) / "__init__.py").is_file() else mod)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("carvi_torch."):
                    out.add(alias.name[len("carvi_torch."):])
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text()))
    return {m for m in out if m}


def _graph() -> dict[str, set[str]]:
    return {_module_name(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def test_no_stage_imports_a_later_stage():
    graph = _graph()
    position = {m: i for i, (_stage, mods) in enumerate(STAGES) for m in mods}
    bad = []
    for mod, deps in graph.items():
        if mod not in position:
            continue
        for dep in deps:
            if dep in position and position[dep] > position[mod] and (mod, dep) not in ALLOWED:
                bad.append(f"{mod} imports {dep}")
    assert not bad, bad
    # the shared maths and thread control import no stage at all
    for base in ("cameras", "runtime", "sdf", "collection", "io.outputs"):
        assert not (graph[base] & set(position)), (base, graph[base] & set(position))


def test_the_checker_sees_a_later_import():
    """The graph reader resolves relative and lazy imports (so the rule above can fail)."""
    graph = _graph()
    assert "mesh" in graph["carve.grids"]  # a lazy import inside a method
    assert "viewpoints.camera_fit" in graph["viewpoints.sfm"]  # a relative import
    assert "carve.native" in graph["carve.dispatch"]


def test_no_import_cycles():
    graph = _graph()
    state: dict[str, int] = {}

    def walk(m, stack):
        state[m] = 1
        for d in graph.get(m, ()):
            if state.get(d) == 1 and not (m == d):
                raise AssertionError("import cycle: " + " -> ".join(stack + [m, d]))
            if d in graph and not state.get(d):
                walk(d, stack + [m])
        state[m] = 2

    for m in graph:
        if not state.get(m):
            # a package's __init__ re-exports its modules: the edges package -> submodule are expected
            walk(m, [])


#: The most lines a function of the package may take beside its docstring (signature included): one screen.
MAX_FUNCTION_LINES = 55


def _lines_beside_docstring(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    first = node.body[0]
    doc = isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str)
    return node.end_lineno - node.lineno + 1 - ((first.end_lineno - first.lineno + 1) if doc else 0)


def test_functions_fit_in_a_screen():
    """Every function (nested ones too) takes at most :data:`MAX_FUNCTION_LINES` lines beside its docstring."""
    long = []
    for path in PACKAGE.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = _lines_beside_docstring(node)
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(PACKAGE)}:{node.lineno} {node.name} ({n} lines)")
    assert not long, long


def test_the_line_count_leaves_out_the_docstring_only():
    """The measure the rule uses: a function's lines less its docstring's."""
    code = 'def f(a,\n      b):\n    """Doc\n\n    more."""\n    x = 1\n    return x\n\ndef g():\n    return 1\n'
    f, g = ast.parse(code).body
    assert (_lines_beside_docstring(f), _lines_beside_docstring(g)) == (4, 2)


def test_pipeline_only_orders_the_stages():
    assert len((PACKAGE / "pipeline.py").read_text().splitlines()) <= 400


def test_peak_memory_without_the_resource_module(imported_alone):
    """Windows has no ``resource``: importing the package and running its process code must not need it."""
    rc, out, err = imported_alone[NO_RESOURCE]
    assert rc == 0 and out.strip() == "ok", err[-2000:]


def test_maxrss_units_per_platform():
    from carvi_torch.runtime import maxrss_to_mb, peak_rss_mb

    assert maxrss_to_mb(5 * 1024, "linux") == 5.0  # kilobytes
    assert maxrss_to_mb(5 * 2 ** 20, "darwin") == 5.0  # bytes
    if sys.platform.startswith("linux"):
        import resource

        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        assert abs(peak_rss_mb() - kb / 1024.0) < 64  # this process, a little later
        assert 10 < peak_rss_mb() < 100_000


def test_writer_processes_are_never_forked():
    """Writer processes start by forkserver (or spawn): a fork of a process whose torch threads may
    hold locks can deadlock. They still write objects."""
    from carvi_torch.io.writer import Writer, start_method

    assert start_method() in ("forkserver", "spawn")
    w = Writer(1)
    try:
        assert w.pool._mp_context.get_start_method() == start_method()
        got = []
        w.submit({"occupancy": None}, got.append)  # a broken job: reported, not raised
        w.drain()
    finally:
        w.close()
    assert len(got) == 1 and got[0]["ok"] is False and "writing failed" in got[0]["reason"]


ALONE = ["pipeline", "config", "viewpoints", "carve", "surrogates", "select"]
#: The code of the ``resource`` check: the package imported where ``import resource`` fails, as on Windows.
NO_RESOURCE = ("import sys; sys.modules['resource'] = None\n"
               "import carvi_torch.pipeline, carvi_torch.runtime as r\n"
               "assert r.resource is None and r.peak_rss_mb() is None and r.peak_rss_mb(children=True) is None\n"
               "print('ok')")

@pytest.fixture(scope="module")
def imported_alone() -> dict[str, tuple[int, str, str]]:
    """Each of ``ALONE`` imported in a fresh process (forked before anything of the package is imported), and
    :data:`NO_RESOURCE`; all at once: name or code -> (status, stdout, stderr)."""
    res = run_each_in_a_fresh_process([f"import carvi_torch.{n}" for n in ALONE] + [NO_RESOURCE])
    return dict(zip(ALONE + [NO_RESOURCE], res))


@pytest.mark.parametrize("name", ALONE)
def test_stage_modules_import_alone(name, imported_alone):
    """Every stage module imports in a fresh process on its own (no hidden order dependency)."""
    rc, _out, err = imported_alone[name]
    assert rc == 0, err[-2000:]


def test_docstring_references_name_what_is_there():
    """Every ``:func:``/``:class:``/``:attr:``/``:meth:``/``:mod:``/``:data:`` reference of the package to a
    ``carvi_torch.*`` name resolves: a module, then attributes (a dataclass's fields and annotated names count),
    so that a moved function leaves no reference to its old home."""
    import importlib
    import re

    def module(parts: list[str]):
        for i in range(len(parts), 0, -1):
            try:
                return i, importlib.import_module(".".join(parts[:i]))
            except ImportError:
                continue

    bad = []
    for p in sorted(PACKAGE.rglob("*.py")):
        for m in re.finditer(r":(?:func|class|attr|meth|mod|data):`~?(carvi_torch(?:\.\w+)+)`", p.read_text()):
            parts = m.group(1).split(".")
            i, obj = module(parts)
            for name in parts[i:]:
                if hasattr(obj, name):
                    obj = getattr(obj, name)
                    continue
                if name in getattr(obj, "__annotations__", {}):  # a field, not a class attribute
                    break
                bad.append(f"{p.relative_to(PACKAGE.parent)}: {m.group(1)}")
                break
    assert not bad, bad


def test_docs_pages_named_in_the_code_exist():
    """Every ``docs/<page>.md``, and every upper-case page (README.md, the report's VENDOR.md), that the package, the
    tools or the tests name is in the repository, so that a merged or renamed page, or one kept elsewhere, leaves
    no pointer (PyTorch3D's own ``docs/notes/cameras.md`` and git's ``commit:docs/...`` excepted)."""
    import re

    root = PACKAGE.parent
    external = {"docs/notes/cameras.md"}
    upper = {f.name for f in [*root.glob("*.md"), *PACKAGE.rglob("*.md")]}
    bad = []
    for folder in ("carvi_torch", "tools", "tests"):
        for p in sorted((root / folder).rglob("*.py")):
            for m in re.finditer(r"(?<![\w/.:])(?:docs/[\w/.-]+?|[A-Z]+)\.md\b", p.read_text()):
                name = m.group(0)
                if name not in external and not (root / name).is_file() and name not in upper:
                    bad.append(f"{p.relative_to(root)}: {name}")
    assert not bad, bad


def test_the_longest_first_files_exist():
    """``make test`` orders whole files by ``conftest.LONGEST_FIRST``: each name there is a test file (a renamed
    file would drop out of the order unnoticed), named once."""
    tests = {p.stem for p in (PACKAGE.parent / "tests").glob("test_*.py")}
    assert [n for n in LONGEST_FIRST if n not in tests] == []
    assert len(set(LONGEST_FIRST)) == len(LONGEST_FIRST)


def test_readme_layout_names_every_module():
    """README's *Layout* names every module of the package (by file name), so that the file list says where each
    stage lives."""
    root = PACKAGE.parent
    text = (root / "README.md").read_text()
    layout = text[text.index("## Layout"):text.index("## Tests")]
    missing = [p.relative_to(PACKAGE).as_posix() for p in sorted(PACKAGE.rglob("*.py"))
               if p.name not in ("__init__.py", "__main__.py") and p.name not in layout]
    assert not missing, missing


def test_package_docstrings_that_list_modules_name_all_of_them():
    """A package whose docstring lists its modules ("Modules, in the order data flows ...", or a list of three or
    more ``:mod:`` references to them) names every one."""
    import ast

    missing = []
    for init in sorted(PACKAGE.rglob("__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text())) or ""
        if "Modules" not in doc and doc.count(":mod:`~carvi_torch.") < 3:
            continue
        for mod in sorted(init.parent.glob("*.py")):
            if mod.stem not in ("__init__", "__main__") and mod.stem not in doc:
                missing.append(f"{init.parent.relative_to(PACKAGE)}: {mod.stem}")
    assert not missing, missing
