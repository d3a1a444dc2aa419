"""The package's import structure: few imports inside functions, each with its reason on its
line; no import cycle among the package's modules (imports inside functions counted); no
import of the repository's folders beside it (benchmarks, experiments, examples, tests); and
the start-up paths that must not load JAX (the commands' --help, bad input, dry runs)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

from helpers import child_env

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "coherent_jax"
# Imports inside functions are kept only for a reason: a JAX-free start-up, an optional
# dependency, a slow import one path needs. Each carries that reason as a comment.
MAX_FUNCTION_IMPORTS = 30


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    """Every module of the package by its dotted name."""
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def function_imports(tree: ast.AST) -> list[ast.Import | ast.ImportFrom]:
    """The imports nested (at any depth) in a function of `tree`."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if in_function and isinstance(child, (ast.Import, ast.ImportFrom)):
                found.append(child)
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    visit(tree, False)
    return found


def imported_modules(tree: ast.AST, name: str, known: set[str], is_package: bool) -> set[str]:
    """The package's modules `tree` (module `name`) imports, wherever the import stands:
    ``from coherent_jax.x import y`` is module ``x.y`` when that is a module, else ``x``."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in known)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the module's package, one level up per extra dot
                package = name.split(".") if is_package else name.split(".")[:-1]
                package = package[: len(package) - (node.level - 1)]
                base = ".".join([*package, *([base] if base else [])])
            for a in node.names:
                target = f"{base}.{a.name}"
                if target in known:
                    out.add(target)
                elif base in known:
                    out.add(base)
    out.discard(name)
    return out


def import_graph() -> dict[str, set[str]]:
    mods = modules()
    known = set(mods)
    return {
        name: imported_modules(ast.parse(path.read_text()), name, known, path.name == "__init__.py")
        for name, path in mods.items()
    }


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def test_imports_inside_functions_are_few_and_each_says_why():
    mods = modules()
    assert len(mods) > 50 and "coherent_jax.run.loop" in mods  # the walk found the package
    kept, silent = [], []
    for name, path in mods.items():
        lines = path.read_text().splitlines()
        for node in function_imports(ast.parse("\n".join(lines))):
            where = f"{name}:{node.lineno}: {lines[node.lineno - 1].strip()}"
            kept.append(where)
            if not any("#" in line for line in lines[node.lineno - 1 : node.end_lineno]):
                silent.append(where)
    assert len(kept) <= MAX_FUNCTION_IMPORTS, "\n".join(kept)
    assert not silent, "imports inside functions without a comment saying why:\n" + "\n".join(silent)


def test_function_imports_are_found_at_any_depth():
    tree = ast.parse(
        "import os\n"
        "def f():\n    import json  # why\n    def g():\n        from a import b\n"
        "class C:\n    def m(self):\n        if True:\n            import re\n"
    )
    assert [n.lineno for n in function_imports(tree)] == [3, 5, 9]


def test_no_import_cycle_among_the_package_modules():
    graph = import_graph()
    assert "coherent_jax.run.training" in graph["coherent_jax.run.launch"]  # a function-level edge counts
    assert "coherent_jax.run.loop" in graph["coherent_jax.run.training"]
    assert cycles(graph) == []


# The repository's folders beside the package: they may import it, never the reverse (the
# wheel ships only ``coherent_jax``).
OUTSIDE = ("benchmarks", "experiments", "examples", "tests")


def outside_imports(tree: ast.AST) -> set[str]:
    """The modules of the repository's other folders (`OUTSIDE`) that `tree` imports, wherever
    the import stands."""
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level:
            names = [node.module or ""]
        else:
            continue
        found.update(n for n in names if n.split(".")[0] in OUTSIDE)
    return found


def test_the_package_imports_nothing_beside_it():
    assert outside_imports(ast.parse("def f():\n    from benchmarks.gradient import g\nimport tests\n")) == {
        "benchmarks.gradient",
        "tests",
    }
    found = [
        f"{name} imports {target}"
        for name, path in modules().items()
        for target in sorted(outside_imports(ast.parse(path.read_text())))
    ]
    assert not found, "\n".join(found)


def test_cycles_are_found():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_from_import_resolves_to_the_module_or_its_package():
    known = {"coherent_jax.run", "coherent_jax.run.loop", "coherent_jax.config"}
    tree = ast.parse(
        "from coherent_jax.run import loop, launch\nfrom coherent_jax.config import Config\n"
        "def f():\n    from . import loop\n"
    )
    assert imported_modules(tree, "coherent_jax.run.x", known, False) == {
        "coherent_jax.run.loop",
        "coherent_jax.run",  # ``launch`` is no module of `known`: its package
        "coherent_jax.config",
    }


def test_commands_start_refuse_and_dry_run_without_jax():
    """--help, bad input and dry runs of train, sweep, evaluate and bench load no JAX."""
    code = (
        "import sys\n"
        "from coherent_jax import evaluate, sweep, train\n"
        "from benchmarks.__main__ import main as bench\n"
        "assert train.main(['--help']) == 0\n"
        "assert train.main(['env=nosuch']) == 2\n"
        "assert train.main(['lr=abc']) == 2\n"
        "assert train.main(['dry_run=true', 'env=pointmass']) == 0\n"
        "assert sweep.main(['--help']) == 0\n"
        "assert sweep.main(['coherent.beta=[]']) == 2\n"
        "grid = ['env=pointmass', 'seeds=2', 'explore=coherent', 'coherent.beta=[0,0.1]']\n"
        "assert sweep.main(['dry_run=true', *grid]) == 0\n"
        "assert evaluate.main(['--help']) == 0\n"
        "assert evaluate.main(['/nonexistent/run']) == 2\n"
        "assert bench(['nosuch']) == 2\n"
        "heavy = sorted(m for m in ('jax', 'flax', 'optax', 'mujoco', 'numpy') if m in sys.modules)\n"
        "assert not heavy, heavy\n"
        "print('ok')\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=child_env(), capture_output=True, text=True, cwd=ROOT
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().endswith("ok")


#: Words with which a small module's docstring gives its reason for standing alone.
REASON_MARKERS = ("stands alone", "module of its own", "module apart", "base apart")
SMALL_MODULE_LINES = 80


def test_small_modules_are_inits_command_shims_or_say_why():
    """A module under 80 lines is an ``__init__``, a command's shim (``python -m``), or its
    docstring says why it stands alone; otherwise it belongs in the module of its idea."""
    unexplained = []
    for name, path in modules().items():
        source = path.read_text()
        if path.name == "__init__.py" or len(source.splitlines()) >= SMALL_MODULE_LINES:
            continue
        if 'if __name__ == "__main__"' in source:
            continue
        doc = (ast.get_docstring(ast.parse(source)) or "").lower()
        if not any(marker in doc for marker in REASON_MARKERS):
            unexplained.append(f"{name} ({len(source.splitlines())} lines)")
    assert not unexplained, "small modules without a reason at their top: " + ", ".join(unexplained)
