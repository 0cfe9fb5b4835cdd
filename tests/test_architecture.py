"""The package's import graph follows docs/architecture.md: no import cycles, no upward imports.

Every ``import`` statement of the package is read from the source (module level and inside functions),
resolved to the module it names, and checked against the layer table below, the same table as in
docs/architecture.md. A module may import from its own layer or a lower one, never a higher one, and the
modules of one layer may not import each other in a cycle. A new module must be given a layer here.
"""
from __future__ import annotations

import ast
from pathlib import Path
from typing import Dict, List, Set, Tuple

import pytest

import torch_hsh

PACKAGE = Path(torch_hsh.__file__).resolve().parent

#: (layer name, module prefixes relative to torch_hsh), lowest layer first. docs/architecture.md has the
#: same table with what each layer is for.
LAYERS: List[Tuple[str, Tuple[str, ...]]] = [
    ("foundations", ("_version", "_checks", "_atomic", "_native", "frames", "quadrature")),
    ("kernel", ("kernel",)),
    ("models", ("bases", "brdf", "nn")),
    ("fitting and I/O", ("fitting", "spectra", "io")),
    ("rendering", ("render", "rti")),
    ("surfaces", ("surface",)),
    ("photometric stereo", ("ps",)),
    ("command line", ("cli", "ps.cli", "rti.cli", "__main__")),
]


def module_names(root: Path, package: str) -> Dict[str, Path]:
    """``{dotted module name: file}`` for every ``.py`` file below ``root`` (``__init__`` names the package)."""
    mods = {}
    for path in sorted(root.rglob("*.py")):
        parts = [package, *path.relative_to(root).with_suffix("").parts]
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = path
    return mods


def import_edges(root: Path, package: str) -> Dict[str, Set[str]]:
    """``{module: modules of the package it imports}``, from every import statement, also inside functions.

    ``from a import b`` counts as an import of the module ``a.b`` where that is a module, otherwise of ``a``.
    """
    mods = module_names(root, package)
    edges: Dict[str, Set[str]] = {}
    for name, path in mods.items():
        here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
        found: Set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), filename=str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = here[: len(here) - node.level + 1] if node.level else []
                origin = ".".join(base + ([node.module] if node.module else []))
                targets = [f"{origin}.{alias.name}" if f"{origin}.{alias.name}" in mods else origin
                           for alias in node.names]
            else:
                continue
            for target in targets:
                while target and target not in mods:  # `import a.b.c` of a package module
                    target = target.rpartition(".")[0]
                if target and target != name:
                    found.add(target)
        edges[name] = found
    return edges


def layer_of(module: str, package: str, layers=LAYERS) -> int:
    """Index of ``module``'s layer (the package itself, its public facade, is above all layers)."""
    if module == package:
        return len(layers)
    rel = module[len(package) + 1:]
    # the longest prefix that names the module decides (``ps.cli`` is above the rest of ``ps``)
    found = [(len(p), k) for k, (_, prefixes) in enumerate(layers) for p in prefixes
             if rel == p or rel.startswith(p + ".")]
    if found:
        return max(found)[1]
    raise KeyError(f"{module} has no layer: add it to LAYERS in tests/test_architecture.py and to "
                   "docs/architecture.md")


def upward_imports(edges: Dict[str, Set[str]], package: str, layers=LAYERS) -> List[str]:
    """``"a -> b (layer x imports layer y)"`` for every import of a higher layer."""
    bad = []
    for src, targets in sorted(edges.items()):
        for dst in sorted(targets):
            a, b = layer_of(src, package, layers), layer_of(dst, package, layers)
            if b > a:
                names = [n for n, _ in layers] + ["the package facade"]
                bad.append(f"{src} -> {dst} ({names[a]} imports {names[b]})")
    return bad


def import_cycles(edges: Dict[str, Set[str]]) -> List[List[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: Dict[str, int] = {}
    low: Dict[str, int] = {}
    stack: List[str] = []
    on_stack: Set[str] = set()
    cycles: List[List[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return cycles


@pytest.fixture(scope="module")
def edges():
    return import_edges(PACKAGE, "torch_hsh")


def test_every_module_has_a_layer(edges):
    for module in edges:
        layer_of(module, "torch_hsh")


def test_no_import_cycles(edges):
    assert import_cycles(edges) == []


def test_no_upward_imports(edges):
    assert upward_imports(edges, "torch_hsh") == []


def test_the_graph_is_read(edges):
    # guards the reader itself: known edges at module level, inside a function and through `from . import`
    assert "torch_hsh.kernel" in edges["torch_hsh.render.images"]
    assert "torch_hsh.cli.common" in edges["torch_hsh.ps.cli"]
    assert "torch_hsh._native" in edges["torch_hsh.kernel"]
    assert any(dst.startswith("torch_hsh.ps") for dst in edges["torch_hsh.cli"])


def _write(root: Path, files: Dict[str, str]) -> None:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_checker_finds_a_cycle_and_an_upward_import(tmp_path):
    _write(tmp_path / "pkg", {
        "__init__.py": "",
        "low.py": "def f():\n    from .high import g\n",      # upward, inside a function
        "high.py": "from . import low\n",
        "sub/__init__.py": "",
        "sub/a.py": "from .b import x\n",
        "sub/b.py": "from ..sub import a\n",                       # cycle a <-> b
    })
    layers = [("low", ("low", "sub")), ("high", ("high", "sub.b"))]
    graph = import_edges(tmp_path / "pkg", "pkg")
    assert import_cycles(graph) == [["pkg.high", "pkg.low"], ["pkg.sub.a", "pkg.sub.b"]]
    assert upward_imports(graph, "pkg", layers) == ["pkg.low -> pkg.high (low imports high)",
                                                    "pkg.sub.a -> pkg.sub.b (low imports high)"]
    assert layer_of("pkg.sub.b", "pkg", layers) == 1 and layer_of("pkg.sub.a", "pkg", layers) == 0
    with pytest.raises(KeyError, match="pkg.other has no layer"):
        layer_of("pkg.other", "pkg", layers)


#: The longest a function's code may be, in lines from its ``def`` to its last line, less its docstring.
MAX_FUNCTION_LINES = 80


def long_functions(root: Path, limit: int = MAX_FUNCTION_LINES) -> List[str]:
    """``"file:line name (N lines)"`` for every function below ``root`` whose code, less its docstring, is longer
    than ``limit`` lines."""
    found = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            lines = node.end_lineno - node.lineno + 1
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                lines -= first.end_lineno - first.lineno + 1
            if lines > limit:
                found.append(f"{path.relative_to(root)}:{node.lineno} {node.name} ({lines} lines)")
    return found


def test_no_function_is_longer_than_the_limit():
    assert long_functions(PACKAGE) == []


def test_long_function_checker_counts_code_not_docstrings(tmp_path):
    body = "".join(f"    x{i} = {i}\n" for i in range(5))
    doc = '    """' + "doc\n" * 30 + '    """\n'
    _write(tmp_path, {"m.py": f"def short():\n{doc}{body}\n\ndef long():\n{body}{body}\n"})
    assert long_functions(tmp_path, limit=8) == ["m.py:40 long (11 lines)"]
    assert long_functions(tmp_path, limit=11) == []
