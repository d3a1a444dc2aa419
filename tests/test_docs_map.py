"""docs/development.md's module map and layers, and docs/walkthrough.md's names, against the code.

* The map (the tables under "Architecture", one per folder, headed ``### `FOLDER/` ``) names
  every module of ``coherent_jax/``, ``benchmarks/`` and ``experiments/`` and nothing that
  does not exist.
* The layers listed there hold for every import of the package, at module level and inside
  functions: a module imports from its own folder or from a layer below its own.
* Every ``coherent_jax.x.y`` name the walk-through gives in backticks resolves (module, then
  attributes), its count of hops is the number of hops it lists, and the package's calls on
  the stack at the first `VecEnv.step` of a real start of ``train`` are hops of that list.
* The package's docstrings and comments, and docs/ and README.md, name modules that exist: a
  ``coherent_jax.x.y`` name resolves (files and syntax trees only, nothing imported), a
  ``path/module.py`` names a file of the repository (docstrings and comments), and no former
  module name of the package (`FORMER_MODULES`) is left.
"""

from __future__ import annotations

import ast
import functools
import importlib
import io
import re
import sys
import tokenize
from collections.abc import Collection
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEVELOPMENT = ROOT / "docs" / "development.md"
WALKTHROUGH = ROOT / "docs" / "walkthrough.md"
MAPPED_TREES = ("coherent_jax", "benchmarks", "experiments")  # every *.py below these must be in the map
PACKAGE = "coherent_jax"


def _section(text: str, heading: str) -> str:
    """The text of the ``## heading`` section, up to the next ``## `` heading."""
    start = text.index(f"\n## {heading}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end >= 0 else len(text)]


def map_entries(text: str) -> dict[str, str]:
    """path (relative to the repository) -> the heading it is listed under, from every table row's
    first cell (its backticked names) under each ``### `FOLDER/` `` heading of "Architecture"."""
    entries: dict[str, str] = {}
    folder = None
    for line in _section(text, "Architecture").splitlines():
        heading = re.fullmatch(r"### `([^`]+/)`", line.strip())
        if heading:
            folder = heading.group(1)
            continue
        if line.startswith("### "):
            folder = None
        if folder is None or not line.startswith("|") or line.startswith("|---"):
            continue
        first = line.split("|")[1]
        for name in re.findall(r"`([^`]+)`", first):
            path = folder + name
            assert path not in entries, f"{path} is listed twice"
            entries[path] = folder
    return entries


def package_modules() -> set[str]:
    return {
        p.relative_to(ROOT).as_posix()
        for tree in MAPPED_TREES
        for p in (ROOT / tree).rglob("*.py")
        if "__pycache__" not in p.parts
    }


def test_map_parser_reads_rows_and_headings():
    text = (
        "# Doc\n\n## Architecture\n\n### `pkg/`\n\n| module | what |\n|---|---|\n"
        "| `a.py` | a |\n| `b.py`, `c.py` | b and c |\n\n### `pkg/sub/`\n\n| module | what |\n"
        "|---|---|\n| `d.py` | d, not `e.py` |\n\n### Not a folder\n\n| `x.py` | x |\n\n## Tests\n\n"
        "### `pkg/`\n\n| `after.py` | outside the section |\n"
    )
    assert map_entries(text) == {
        "pkg/a.py": "pkg/",
        "pkg/b.py": "pkg/",
        "pkg/c.py": "pkg/",
        "pkg/sub/d.py": "pkg/sub/",
    }


def test_every_module_is_in_the_map():
    mapped = set(map_entries(DEVELOPMENT.read_text()))
    missing = sorted(package_modules() - mapped)
    assert not missing, f"modules docs/development.md's map does not name: {missing}"


def test_the_map_names_only_what_exists():
    gone = sorted(p for p in map_entries(DEVELOPMENT.read_text()) if not (ROOT / p).exists())
    assert not gone, f"docs/development.md's map names what does not exist: {gone}"


def test_each_folder_has_its_own_table():
    """Each module is listed under its own folder's heading: one table per folder."""
    folders = {p.rsplit("/", 1)[0] + "/" for p in package_modules()}
    headings = set(map_entries(DEVELOPMENT.read_text()).values())
    assert folders <= headings, f"folders without a table: {sorted(folders - headings)}"


# ------------------------------------------------------------------------------- layers
def layers(text: str) -> list[list[str]]:
    """The numbered layers of "Architecture" / "Layers": each a list of units, a unit a
    top-level module (``train.py``), a folder (``run/``) or one module of a folder
    (``policy/hub.py``), relative to the package."""
    block = _section(text, "Architecture").split("### Layers", 1)[1].split("\n### ", 1)[0]
    found = []
    for line in block.splitlines():
        m = re.fullmatch(r"\s+(\d+)\.\s+(?:[A-Za-z ]+:)?\s*(.+)", line)
        if m:
            assert int(m.group(1)) == len(found) + 1, line
            found.append(m.group(2).split())
    return found


def unit_of(module: str, units: Collection[str] | None = None) -> str:
    """A module's unit in the layers: its top-level file, else the most specific of ``units``
    (by default the layers' own) that holds it: the module itself (``policy/hub.py``), its
    folder, a folder above it; else its top folder."""
    units = {u for layer in layers(DEVELOPMENT.read_text()) for u in layer} if units is None else units
    parts = module.split(".")[1:]
    path = ROOT / PACKAGE / Path(*parts) if parts else ROOT / PACKAGE
    if path.is_dir():  # a package: its __init__.py
        parts = [*parts, "__init__"]
    if len(parts) == 1:
        return parts[0] + ".py"
    candidates = ["/".join(parts) + ".py"] + ["/".join(parts[:k]) + "/" for k in range(len(parts) - 1, 0, -1)]
    return next((c for c in candidates if c in units), parts[0] + "/")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _exists(module: str) -> bool:
    base = ROOT / Path(*module.split("."))
    return base.with_suffix(".py").exists() or (base / "__init__.py").exists()


def imports_of(path: Path, source: str | None = None) -> set[str]:
    """Every module of the package that `path` (or `source`, as if at `path`) imports,
    wherever the import statement is."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text() if source is None else source)):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                source = f"{base}.{node.module}" if node.module else base
            else:
                source = node.module or ""
            # ``from pkg import mod`` imports the module; ``from mod import name`` the module.
            targets = [f"{source}.{a.name}" if _exists(f"{source}.{a.name}") else source for a in node.names]
        else:
            continue
        found.update(t for t in targets if t.startswith(PACKAGE + ".") and _exists(t))
    return found


def test_layer_check_sees_function_level_and_relative_imports():
    source = (
        "from . import mujoco_task\nfrom .spec import TaskSpec\nimport json\n\n"
        "def f():\n    from coherent_jax.run import launch\n    import coherent_jax.train\n"
        "    from coherent_jax.config import Config\n"
    )
    found = imports_of(ROOT / PACKAGE / "envs" / "quiet.py", source)
    assert found == {
        "coherent_jax.envs.mujoco_task",
        "coherent_jax.envs.spec",
        "coherent_jax.run.launch",
        "coherent_jax.train",
        "coherent_jax.config",
    }
    assert unit_of("coherent_jax.run.launch") == "run/"
    assert unit_of("coherent_jax.run.launch", {"run/", "run/evaluation.py"}) == "run/"
    assert unit_of("coherent_jax.run.evaluation", {"run/", "run/evaluation.py"}) == "run/evaluation.py"
    assert unit_of("coherent_jax.exploration.coherent", {"exploration/", "exploration/coherent/"}) == (
        "exploration/coherent/"
    )
    assert unit_of("coherent_jax.exploration.coherent.filter") == "exploration/coherent/"
    assert unit_of("coherent_jax.exploration") == "exploration/"
    assert unit_of("coherent_jax.train") == "train.py"
    assert unit_of("coherent_jax.config.cli") == "config/"
    assert unit_of("coherent_jax") == "__init__.py"


def test_imports_follow_the_layers():
    stated = layers(DEVELOPMENT.read_text())
    level = {unit: i for i, units in enumerate(stated) for unit in units}
    modules = sorted((ROOT / PACKAGE).rglob("*.py"))
    units = {unit_of(_module_name(p), level) for p in modules}
    assert units == set(level), f"units the layers miss: {sorted(units - set(level))}; " + (
        f"listed but absent: {sorted(set(level) - units)}"
    )
    upward = []
    for path in modules:
        unit = unit_of(_module_name(path), level)
        for target in sorted(imports_of(path)):
            other = unit_of(target, level)
            if other != unit and level[other] <= level[unit]:
                upward.append(f"{path.relative_to(ROOT)} ({unit}) imports {target} ({other})")
    assert not upward, "imports against docs/development.md's layers:\n" + "\n".join(upward)


# --------------------------------------------------------------------------- walk-through
def walkthrough_names(text: str) -> list[str]:
    """Every backticked dotted name of the package in `text`, in order, without repeats."""
    names = re.findall(r"`(coherent_jax(?:\.[A-Za-z_][A-Za-z0-9_]*)+)`", text)
    return list(dict.fromkeys(names))


def resolve(name: str):
    """The object `name` names: the longest importable module prefix, then attributes."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            obj = getattr(obj, attr)
        return obj
    raise ModuleNotFoundError(name)


def test_resolve_refuses_a_name_that_does_not_exist():
    assert resolve("coherent_jax.envs.vec_env.VecEnv.step") is not None
    with pytest.raises(AttributeError):
        resolve("coherent_jax.envs.vec_env.VecEnv.stepp")
    with pytest.raises(AttributeError):
        resolve("coherent_jax.run.launcher.run")


def test_every_name_of_the_walkthrough_exists():
    names = walkthrough_names(WALKTHROUGH.read_text())
    assert len(names) >= 30, names  # the walk-through names each function on the way
    unresolved = []
    for name in names:
        try:
            resolve(name)
        except (AttributeError, ModuleNotFoundError) as exc:
            unresolved.append(f"{name}: {exc}")
    assert not unresolved, "names in docs/walkthrough.md that do not exist:\n" + "\n".join(unresolved)


def test_walkthrough_hop_count_is_its_list():
    """The hops from ``num_envs=`` to `VecEnv.step`: the stated number is the list's length,
    each hop a numbered row naming the function it calls."""
    text = WALKTHROUGH.read_text()
    stated = re.search(r"\*\*(\d+) hops\*\*", text)
    assert stated, "the walk-through states no hop count"
    table = text.split("<!-- hops -->", 2)[1]
    rows = re.findall(r"^\| (\d+) \| [^|]*`(coherent_jax\.[\w.]+)`", table, flags=re.M)
    assert [int(n) for n, _ in rows] == list(range(1, len(rows) + 1))
    assert int(stated.group(1)) == len(rows)
    assert rows[-1][1] == "coherent_jax.envs.vec_env.VecEnv.step"


def _hop_rows() -> list[str]:
    """The first package name of each row of the walk-through's hop list, in order."""
    table = WALKTHROUGH.read_text().split("<!-- hops -->", 2)[1]
    return re.findall(r"^\| \d+ \| [^|]*`(coherent_jax\.[\w.]+)`", table, flags=re.M)


def test_the_calls_on_the_stack_at_the_env_step_are_hops_in_order(tmp_path, monkeypatch):
    """A real start of ``train`` (``pointmass``, stopped at its first `VecEnv.step`, while the
    iteration is traced): every function of the package on the stack there is a hop of the
    list, in the list's order (the hops not on the stack returned their value before)."""
    from coherent_jax import train
    from coherent_jax.envs import vec_env

    class Reached(Exception):
        pass

    seen: list[str] = []

    def step(self, state, action):
        frame = sys._getframe(1)
        while frame is not None:
            module = frame.f_globals.get("__name__", "")
            if module.startswith(PACKAGE + "."):
                qualname = frame.f_code.co_qualname.split(".<locals>.")[0]  # a closure: its function
                seen.append(f"{module}.{qualname}")
            frame = frame.f_back
        raise Reached

    monkeypatch.setattr(vec_env.VecEnv, "step", step)
    argv = [
        "env=pointmass",
        "num_envs=8",
        f"run_dir={tmp_path / 'run'}",
        "progress=false",
        "tensorboard=false",
    ]
    with pytest.raises(Reached):
        train.main(argv)
    stack = [*reversed(seen), "coherent_jax.envs.vec_env.VecEnv.step"]
    assert stack[0] == "coherent_jax.train.main"
    rows, at = _hop_rows(), 0
    for name in stack[1:]:
        assert name in rows[at:], f"{name}, on the stack at VecEnv.step, is not a later hop of the list"
        at = rows.index(name, at) + 1
    assert at == len(rows)  # the last frame is the last hop, VecEnv.step
    on_stack = re.search(r"\*\*(\d+) of them\*\* are on the stack", WALKTHROUGH.read_text())
    assert on_stack and int(on_stack.group(1)) == len(stack) - 1  # train.main is where the hops start


# ------------------------------------------------------------------ module names in prose
#: The package's former module names, which prose must no longer use: a whole word
#: (``coherent_filter``) or a dotted name below the package (``run.policy``, also matched
#: after ``coherent_jax.``). A move adds the names it retires; none may exist again.
FORMER_MODULES = (
    *("coherent_filter", "coherent_joint", "coherent_exact", "coherent_layer", "coherent_mc"),
    *("bench_distributed", "bench_physics", "bench_sac", "bench_gradient", "sweep_resume", "sweep_table"),
    *("exploration.registry", "run.policy", "policy.agent"),
    *("config.legacy", "config.declare", "config.limits", "config.presets"),
    *("envs.native", "envs.task", "envs.user_task", "envs.make", "envs.classic", "envs.pointmass"),
    *("envs.brax_native", "envs.dmc_native", "envs.mjx_physics"),
    *(
        "run.single",
        "run.runs",
        "run.stop",
        "run.tracking",
        "run.callbacks",
        "run.sharding",
        "run.collective",
    ),
    *("run.state_bytes", "run.video", "run.video_path", "run.provenance", "run.runlock", "run.divergence"),
    *("coherent_jax.sweeps", "sweeps.plan", "sweeps.program", "sweeps.resume", "sweeps.table"),
)
#: ``.py`` names the package's prose gives of other projects' files, or as placeholders.
FOREIGN_FILES = {
    *("spinup/algos/pytorch/ppo/ppo.py", "vpg/vpg.py", "sac/sac.py", "ppo.py", "vpg.py"),
    *("pendulum.py", "continuous_mountain_car.py", "_v5.py", "src/models/distributions.py"),
    *("path/to/file.py", "FILE.py", "envs.py"),
}
DOTTED = re.compile(r"(?<![\w.])coherent_jax(?:\.[A-Za-z_]\w*)+")
PY_PATH = re.compile(r"(?<![\w./-])((?:[\w.-]+/)*[\w-]+\.py)\b")
_FORMER_ALTERNATIVES = "|".join(map(re.escape, FORMER_MODULES))
FORMER = re.compile(rf"(?<![\w.])(?:coherent_jax\.)?({_FORMER_ALTERNATIVES})(?!\w)")


def prose_of(path: Path) -> list[tuple[int, str]]:
    """(line, text) of every docstring and comment of a Python file; of every line of a Markdown one."""
    source = path.read_text()
    if path.suffix == ".md":
        return list(enumerate(source.splitlines(), 1))
    found = [
        (node.body[0].lineno, ast.get_docstring(node, clean=False))
        for node in ast.walk(ast.parse(source))
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef))
        and ast.get_docstring(node, clean=False)
    ]
    tokens = tokenize.generate_tokens(io.StringIO(source).readline)
    return found + [(t.start[0], t.string) for t in tokens if t.type == tokenize.COMMENT]


def _top_names(body: list[ast.stmt]) -> dict[str, ast.AST | str | None]:
    """What a module or class body defines: name -> its class, the dotted module it is
    imported from, or None; a module with ``__getattr__`` also defines its dicts' string keys."""
    names: dict[str, ast.AST | str | None] = {}
    for node in body:
        if isinstance(node, (ast.If, ast.Try)):
            names.update(_top_names(node.body + node.orelse + getattr(node, "handlers", [])))
        elif isinstance(node, ast.ExceptHandler):
            names.update(_top_names(node.body))
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names[node.name] = node if isinstance(node, ast.ClassDef) else None
        elif isinstance(node, ast.ImportFrom):
            names.update({a.asname or a.name: f"{node.module}.{a.name}" for a in node.names})
        elif isinstance(node, ast.Import):
            names.update({(a.asname or a.name).split(".")[0]: None for a in node.names})
        elif isinstance(node, (ast.Assign, ast.AnnAssign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update({n.id: None for t in targets for n in ast.walk(t) if isinstance(n, ast.Name)})
    if "__getattr__" in names:
        for node in ast.walk(ast.Module(body=body, type_ignores=[])):
            if isinstance(node, ast.Dict):
                names.update({k.value: None for k in node.keys if isinstance(k, ast.Constant)})
    return names


@functools.cache
def _module_file(dotted: str) -> Path | None:
    base = ROOT / Path(*dotted.split("."))
    return next((f for f in (base.with_suffix(".py"), base / "__init__.py") if f.is_file()), None)


@functools.cache
def _module_names(dotted: str) -> dict[str, ast.AST | str | None]:
    return _top_names(ast.parse(_module_file(dotted).read_text()).body)


def name_exists(name: str) -> bool:
    """Whether ``coherent_jax.x.y.Attr.attr`` names something: the longest prefix that is a
    module file, then a name it defines or imports (followed to its own module), then a
    class's attribute (its body, ``self.x = ...`` in its methods, a base class of the package).
    Deeper attributes, and attributes of classes with other bases, are not checked."""
    parts = name.split(".")
    cut = next((k for k in range(len(parts), 0, -1) if _module_file(".".join(parts[:k]))), 0)
    if not cut or cut == len(parts):
        return bool(cut)
    names = _module_names(".".join(parts[:cut]))
    found = names.get(parts[cut], False)
    if isinstance(found, str) and found.startswith(PACKAGE + "."):  # imported: where it is defined
        return name_exists(".".join([found, *parts[cut + 1 :]]))
    if found is False or len(parts) == cut + 1 or not isinstance(found, ast.ClassDef):
        return found is not False
    return _class_has(found, names, parts[cut + 1])


def _class_has(cls: ast.ClassDef, module_names: dict, attr: str) -> bool:
    own = set(_top_names(cls.body))
    own |= {
        t.attr
        for node in ast.walk(cls)
        for t in getattr(node, "targets", [getattr(node, "target", None)])
        if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self"
    }
    if attr in own:
        return True
    for base in (b.id for b in cls.bases if isinstance(b, ast.Name)):
        where = module_names.get(base, False)
        if isinstance(where, ast.ClassDef):
            if _class_has(where, module_names, attr):
                return True
        elif isinstance(where, str) and where.startswith(PACKAGE + "."):
            if name_exists(f"{where}.{attr}"):
                return True
        else:  # a base of another library: its attributes are not checked
            return True
    return False


def _repository_files() -> list[str]:
    return [
        p.relative_to(ROOT).as_posix()
        for p in ROOT.rglob("*.py")
        if not any(part.startswith(".") or part == "__pycache__" for part in p.relative_to(ROOT).parts)
    ]


def stale_names(path: Path, text: str, line: int, files: list[str]) -> list[str]:
    """The module names of `text` (at `line` of `path`) that name nothing of the repository."""
    where = f"{path.relative_to(ROOT)}:{line}"
    found = [f"{where}: {m.group(0)} (a former module)" for m in FORMER.finditer(text)]
    found += [f"{where}: {n}" for n in {m.group(0) for m in DOTTED.finditer(text)} if not name_exists(n)]
    if path.suffix == ".py":
        for name in {m.group(1) for m in PY_PATH.finditer(text)} - FOREIGN_FILES:
            if not any(f == name or f.endswith("/" + name) for f in files):
                found.append(f"{where}: {name}")
    return found


def test_the_prose_check_finds_names_that_name_nothing():
    files = ["coherent_jax/policy/net.py", "tests/test_docs_map.py"]
    text = (
        "`coherent_jax.policy.net.PolicyNet.mean_action`, `coherent_jax.policy.Policy.predict`,"
        " `coherent_jax.Policy`, policy/net.py, tests/test_docs_map.py, coherent/filter.py\n"
        "`coherent_jax.policy.net.PolicyNet.act`, `coherent_jax.run.gone`, policy/gone.py,"
        " `coherent_filter.log_marginals`, coherent_jax.run.policy.Policy, test_coherent_filter.py"
    )
    stale = {s.split(": ", 1)[1] for s in stale_names(ROOT / PACKAGE / "x.py", text, 1, files)}
    assert stale == {
        *("coherent_jax.policy.net.PolicyNet.act", "coherent_jax.run.gone", "coherent_jax.run.policy.Policy"),
        *("coherent_jax.run.policy (a former module)", "coherent_filter (a former module)"),
        *("policy/gone.py", "coherent/filter.py", "test_coherent_filter.py"),
    }


def test_former_module_names_are_gone():
    back = [n for n in FORMER_MODULES if _exists(f"{PACKAGE}.{n}") or list((ROOT / PACKAGE).rglob(f"{n}.py"))]
    assert not back, f"FORMER_MODULES names modules that exist: {back}"


#: The one place prose names former modules on purpose: docs/api.md's table of the deprecated
#: names (tests/test_compat.py holds each of them to its successor instead).
DEPRECATIONS = (ROOT / "docs" / "api.md", "Deprecated names")


def _current_prose(path: Path) -> list[tuple[int, str]]:
    """`prose_of`, without the lines of the deprecations' section of docs/api.md."""
    lines = prose_of(path)
    if path != DEPRECATIONS[0]:
        return lines
    section = _section(path.read_text(), DEPRECATIONS[1]).strip("\n").splitlines()
    start = next(n for n, text in lines if text == section[0])
    return [(n, text) for n, text in lines if not start <= n < start + len(section)]


def test_the_deprecations_section_alone_is_left_out():
    kept = {text for _, text in _current_prose(DEPRECATIONS[0])}
    assert "## Deprecated names" not in kept and "## Every public name" in kept
    assert any("coherent_jax.run.policy" in text for _, text in prose_of(DEPRECATIONS[0]))


def test_docstrings_comments_and_docs_name_modules_that_exist():
    files = _repository_files()
    prose = [
        *sorted((ROOT / PACKAGE).rglob("*.py")),
        *sorted((ROOT / "docs").glob("*.md")),
        ROOT / "README.md",
    ]
    stale = [
        s
        for path in prose
        for line, text in _current_prose(path)
        for s in stale_names(path, text, line, files)
    ]
    assert not stale, "names of modules that do not exist:\n" + "\n".join(stale)
