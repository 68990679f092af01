"""The package's shape, checked from its source: no import cycles, no hidden imports, one
place per numerical rule, twins independent of the code they check."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jaxbvh"

# modules a NumPy twin may import from the library: neutral rules and layouts, other twins
TWIN_MAY_IMPORT = re.compile(r"^jaxbvh\.(numerics|draws|tree\.(layout|walks|frame|interchange)"
                             r"|.*_reference|.*_rules|wide\.box_tests)$")
# numerical rules that live in jaxbvh.numerics only (pattern, what it is)
RULES = [
    (r"2\.0 \*\* -20", "the tie tolerance"),
    (r"64 \* np\.finfo", "the 64 eps margin"),
    (r"\bj?np\.frexp\(", "the power-of-two area scale"),
    (r"^def _take\(", "the bounded gather"),
    (r"^def _?working_dtype\(", "the working dtype"),
    (r"(\w+)\[(\.\.\., |:, )?0\] \* \1\[(\.\.\., |:, )?1\] \+ \1\[", "the box half-area (numerics.half_area)"),
]
RULE_HOMES = {"numerics.py", "tree/frame.py"}  # frame.py: the frame's own scale (not an area scale)


def modules() -> dict[str, Path]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out[".".join(parts)] = path
    return out


def imported(tree: ast.AST, names: set[str], top_level_only: bool):
    """jaxbvh modules imported by ``tree`` (a module's AST): ``(module, line, in_function)``."""
    def resolve(base, attr):
        full = f"{base}.{attr}"
        return full if full in names else base

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.ImportFrom) and child.module and child.module.split(".")[0] == "jaxbvh":
                for alias in child.names:
                    yield resolve(child.module, alias.name), child.lineno, in_function
            elif isinstance(child, ast.Import):
                for alias in child.names:
                    if alias.name.split(".")[0] == "jaxbvh":
                        yield alias.name, child.lineno, in_function
            if not (top_level_only and inside):
                yield from visit(child, inside)

    yield from visit(tree, False)


@pytest.fixture(scope="module")
def graph():
    mods = modules()
    names = set(mods)
    edges = {}
    for name, path in mods.items():
        tree = ast.parse(path.read_text(), str(path))
        edges[name] = {m for m, _, inside in imported(tree, names, True) if not inside and m in names}
    return mods, edges


def test_no_import_cycles(graph):
    """Module-level imports form no cycle (a package imports its own ``__init__`` too)."""
    _, edges = graph
    state = {}
    cycle = []

    def dfs(node, stack):
        state[node] = "open"
        for nxt in sorted(edges[node]):
            # a module importing its parent package runs that __init__ first
            if state.get(nxt) == "open":
                cycle.append(stack[stack.index(nxt):] + [nxt])
            elif nxt not in state:
                dfs(nxt, stack + [nxt])
        state[node] = "closed"

    for node in sorted(edges):
        if node not in state:
            dfs(node, [node])
    cycles = [c for c in cycle if not (len(c) == 2 and c[0] == c[1])]
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


#: modules whose purpose is to put off importing the library (and JAX) until it is needed:
#: the console script's front answers --help without JAX (jaxbvh.cli.front)
DEFERS_IMPORTS = {"jaxbvh.cli.front", "jaxbvh.rays.native"}  # and the native ray engine: numba on first use


def test_no_library_import_inside_a_function():
    mods = modules()
    names = set(mods)
    found = []
    for name, path in mods.items():
        if name in DEFERS_IMPORTS:
            continue
        tree = ast.parse(path.read_text(), str(path))
        found += [f"{name}:{line} imports {m}" for m, line, inside in imported(tree, names, False) if inside]
    assert not found, "\n".join(found)


def test_twins_import_no_jax_module(graph):
    """A twin (``*_reference``) checks its JAX module independently: it imports only
    neutral rules, layouts and other twins."""
    _, edges = graph
    bad = [f"{name} imports {m}" for name, deps in edges.items() if name.endswith("_reference")
           for m in deps if not TWIN_MAY_IMPORT.match(m)]
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("pattern, rule", RULES)
def test_each_rule_is_written_once(pattern, rule):
    where = []
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE).as_posix()
        if rel in RULE_HOMES:
            continue
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if re.search(pattern, line) and not line.lstrip().startswith(("#", '"', "``")):
                where.append(f"jaxbvh/{rel}:{i}: {line.strip()}")
    assert not where, f"{rule} is copied outside jaxbvh.numerics:\n" + "\n".join(where)


def test_every_twin_sits_beside_its_module():
    mods = modules()
    lonely = [n for n in mods if n.endswith("_reference") and n[: -len("_reference")] not in mods]
    assert not lonely, f"twins without a module of the same name beside them: {lonely}"


TESTS = Path(__file__).resolve().parent
# the package's shape, its notebooks, its documentation site and the examples on its pages,
# the compilation cache that `import jaxbvh` turns on, the engine rule every query follows
WHOLE_PACKAGE_TESTS = {"test_architecture.py", "test_notebooks.py", "test_docs.py", "test_docs_examples.py",
                       "test_compile_cache.py", "test_compile_policy.py", "test_program_store.py",
                       "test_engines.py"}


def test_tests_follow_the_packages():
    """Each test module sits in the folder of the package it tests (``tests/optimize/`` for
    ``jaxbvh/optimize/``); only whole-package checks sit at the top."""
    for path in TESTS.rglob("test_*.py"):
        folder = path.parent.relative_to(TESTS)
        if folder == Path("."):
            assert path.name in WHOLE_PACKAGE_TESTS, f"{path.name}: move it into the folder of its package"
        else:
            assert (PACKAGE / folder / "__init__.py").exists(), f"tests/{folder}: no package jaxbvh/{folder}"


def test_tests_use_public_names():
    """Tests reach the library by its public names (a step they need is public):
    no ``from jaxbvh... import _name`` and no ``module._name`` of a library module."""
    for path in TESTS.rglob("*.py"):
        tree = ast.parse(path.read_text())
        library = {alias.asname or alias.name for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
                   and (node.module or "").startswith("jaxbvh") for alias in node.names}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxbvh"):
                assert not [a.name for a in node.names if a.name.startswith("_")], f"{path.name}:{node.lineno}"
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                    and isinstance(node.value, ast.Name) and node.value.id in library | {"jaxbvh"}):
                assert node.attr == "_cache_size", f"{path.name}:{node.lineno}: {node.value.id}.{node.attr}"


def test_every_top_level_program_is_stored():
    """Every jitted function at a module's top level goes through
    :func:`jaxbvh.program_store.stored_jit`, so a warm process loads it instead of tracing
    it again (a plain ``jax.jit`` there would be traced in every process)."""
    plain = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.name == "program_store.py":
            continue
        tree = ast.parse(path.read_text())
        for node in tree.body:  # top level only: programs built inside functions are per call
            decorators = node.decorator_list if isinstance(node, ast.FunctionDef) else []
            values = [node.value] if isinstance(node, ast.Assign) else []
            for expr in [*decorators, *values]:
                text = ast.unparse(expr)
                if re.match(r"(partial\()?jax\.jit\b", text):
                    plain.append(f"{path.relative_to(PACKAGE)}:{expr.lineno}: {text[:60]}")
    assert not plain, "\n".join(plain)
