"""No two modules of stnh_tf need each other, not even through an import inside a function
(docs/conventions.md: move what both need below them). The imports are read with ``ast`` from the
source (every ``import`` and ``from ... import`` anywhere in a module, relative ones resolved), so
a lazy import cannot hide a cycle."""

import ast
import os

import pytest

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def package_modules(package="stnh_tf") -> dict:
    """``{dotted module name: path}`` of every ``.py`` file below ``package`` (a package's
    ``__init__.py`` under the package's own name)."""
    found = {}
    for folder, _, names in os.walk(os.path.join(REPO, package)):
        for name in names:
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                dotted = os.path.relpath(path, REPO)[:-3].replace(os.sep, ".")
                found[dotted.removesuffix(".__init__")] = path
    return found


def imports_of(name, path, modules) -> set:
    """The modules of ``modules`` that the module ``name`` (source at ``path``) imports anywhere,
    functions included: ``from p import m`` counts as ``p.m`` where ``m`` is a module, else as
    ``p``; relative imports are resolved against ``name``'s package."""
    package = name if path.endswith("__init__.py") else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(open(path, encoding="utf-8").read(), path)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[:len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([node.module] if node.module else []))
            submodules = {f"{base}.{alias.name}" for alias in node.names} & set(modules)
            found |= submodules
            if len(submodules) < len(node.names):
                found.add(base)
    return {m for m in found if m in modules and m != name}


def find_cycle(graph) -> list | None:
    """One cycle ``[m1, m2, ..., m1]`` of the directed ``graph`` (``{node: set of nodes}``), or
    ``None`` (depth-first search, the nodes in sorted order)."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def test_the_cycle_finder_finds_a_lazy_import_cycle(tmp_path):
    """The reader and the search on a package made here: ``a`` imports ``b`` at its top, ``b``
    imports ``a`` inside a function through a relative import."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "__init__.py").write_text("")
    (tmp_path / "pkg" / "a.py").write_text("from pkg import b\n")
    (tmp_path / "pkg" / "b.py").write_text("def f():\n    from . import a\n    return a\n")
    (tmp_path / "pkg" / "c.py").write_text("import pkg.a\nfrom pkg.b import f\n")
    modules = {f"pkg.{n}": str(tmp_path / "pkg" / f"{n}.py") for n in "abc"}
    modules["pkg"] = str(tmp_path / "pkg" / "__init__.py")
    graph = {m: imports_of(m, p, modules) for m, p in modules.items()}
    assert graph == {"pkg": set(), "pkg.a": {"pkg.b"}, "pkg.b": {"pkg.a"},
                     "pkg.c": {"pkg.a", "pkg.b"}}
    assert find_cycle(graph) == ["pkg.a", "pkg.b", "pkg.a"]
    graph["pkg.b"] = set()
    assert find_cycle(graph) is None


def test_no_module_of_stnh_tf_imports_one_that_imports_it():
    modules = package_modules()
    assert len(modules) > 50
    graph = {m: imports_of(m, p, modules) for m, p in modules.items()}
    cycle = find_cycle(graph)
    if cycle:
        pytest.fail("import cycle: " + " -> ".join(cycle))
