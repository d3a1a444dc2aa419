"""The public names of before, kept working until they go: each warns once, naming its successor.

A renamed attribute of a module is answered by that module's ``__getattr__``
(`module_getattr`: the old name, the new one's dotted path); a module that moved
(``coherent_jax.runs`` -> ``coherent_jax.run.checkpoint``) is imported through `FormerModules`, a
finder on ``sys.meta_path`` that the package installs, so ``import``, ``from ... import`` and
attribute access all still work. docs/api.md lists them with the release that removes them
(`REMOVED_IN`).

Both resolve the new name when it is used (``importlib`` by name, as the package's lazy
attributes do), so the table of former names costs no import. Each former name warns once per
process (`DeprecationWarning`, which Python shows for code run as ``__main__`` and pytest shows
in a user's tests), pointed at the caller's line.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from collections.abc import Callable, Mapping
from typing import Any

#: the release that removes every name of this module's tables.
REMOVED_IN = "0.3"

_warned: set[str] = set()


def warn_once(old: str, new: str, stacklevel: int = 3) -> None:
    """One `DeprecationWarning` per process for `old`: ``old is deprecated: use new (removed in 0.3)``.
    `stacklevel` 3 points at the line that used `old` when called from the function it reaches."""
    if old in _warned:
        return
    _warned.add(old)
    warnings.warn(
        f"{old} is deprecated: use {new} (removed in coherent_jax {REMOVED_IN})",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


def resolve(dotted: str) -> Any:
    """The object ``package.module.Name`` (the longest importable module, then attributes)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            found: Any = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError:
            continue
        for attr in parts[cut:]:
            found = getattr(found, attr)
        return found
    raise ModuleNotFoundError(dotted)


def module_getattr(module: str, former: Mapping[str, str], stacklevel: int = 3) -> Callable[[str], Any]:
    """A ``__getattr__`` for `module` that answers its former names (old name -> the new
    name's dotted path), warning once each, and raises `AttributeError` for anything else.
    `stacklevel` 4 where another ``__getattr__`` calls it."""

    def __getattr__(name: str) -> Any:
        if name not in former:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warn_once(f"{module}.{name}", former[name], stacklevel)
        return resolve(former[name])

    return __getattr__


class FormerModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports a moved module by its former name: ``{former: (new module, {old attr: new attr})}``.

    The former module is a small module of its own whose attributes are the new module's
    (renamed where the table says), so the new module's ``__name__`` and ``__spec__`` stay its
    own; importing it warns once, and so does each renamed attribute."""

    def __init__(self, table: Mapping[str, tuple[str, Mapping[str, str]]]) -> None:
        self.table = dict(table)

    def find_spec(self, fullname: str, path: Any = None, target: Any = None):
        if fullname not in self.table:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType | None:
        return None  # the default module object

    def exec_module(self, module: types.ModuleType) -> None:
        new, renamed = self.table[module.__name__]
        warn_once(module.__name__, new)  # at the importing line: warnings skips importlib's frames
        module.__doc__ = f"The former name of `{new}` (removed in coherent_jax {REMOVED_IN})."

        def __getattr__(name: str) -> Any:
            if name.startswith("__"):
                raise AttributeError(name)
            if name in renamed:
                warn_once(f"{module.__name__}.{name}", f"{new}.{renamed[name]}")
            return getattr(importlib.import_module(new), renamed.get(name, name))

        module.__getattr__ = __getattr__  # type: ignore[method-assign]


def install(table: Mapping[str, tuple[str, Mapping[str, str]]]) -> None:
    """Puts a `FormerModules` of `table` at the end of ``sys.meta_path`` (once), behind the
    finders of the modules that exist."""
    if not any(isinstance(f, FormerModules) for f in sys.meta_path):
        sys.meta_path.append(FormerModules(table))
