"""How each layer package (``core``, ``io``, ``pipeline``) exports its public names.

A layer's ``__init__`` lists every public name of its modules (``from lidarcal_ros.core
import Calibrator``) but imports a module only when one of its names is first asked for:
importing a package would otherwise load every module of the layer (numba's compiled loops,
matplotlib, rosbags' type store), which the command line and the nodes must not pay for at
start. :func:`lazy_exports` builds the package's ``__getattr__``, ``__dir__`` (PEP 562)
and ``__all__`` from a table of module -> names; ``test/test_exports.py`` holds the table to
the modules' own ``__all__``.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any


def lazy_exports(package: str, modules: Mapping[str, Sequence[str]]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
    """``__getattr__``, ``__dir__`` and ``__all__`` of ``package`` exporting ``modules``.

    Parameters
    ----------
    package
        The package's ``__name__``.
    modules
        Each module of the package (its name relative to ``package``) -> the public names it
        defines (its ``__all__``).
    """
    table = {name: module for module, names in modules.items() for name in names}

    def __getattr__(name: str) -> Any:
        module = table.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{module}"), name)

    def __dir__() -> list[str]:
        # What the package itself holds (its submodules once imported, __name__, ...) and
        # what it exports, as dir() of a package that imported its names would list.
        return sorted(set(vars(sys.modules[package])) | set(table))

    return __getattr__, __dir__, sorted(table)


__all__ = ["lazy_exports"]
