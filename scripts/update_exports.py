"""Rewrite the export table at the end of each layer package's ``__init__.py`` from its modules'
own ``__all__`` (``test/test_exports.py`` fails until this has been run after a change of them).

    .venv/bin/python scripts/update_exports.py            # every layer
    .venv/bin/python scripts/update_exports.py core io    # these
"""

from __future__ import annotations

import ast
import sys
import textwrap
from pathlib import Path

LAYERS = ("core", "io", "pipeline", "cli", "nodes", "ros")
MARK_BEGIN = "# --- exports (generated from the modules' __all__; test/test_exports.py checks) ---"
MARK_END = "# --- end of exports ---"
ROOT = Path(__file__).resolve().parent.parent


def module_all(path: Path) -> list[str] | None:
    """The ``__all__`` a module's source assigns (None without one)."""
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets):
            return [ast.literal_eval(e) for e in node.value.elts]  # type: ignore[attr-defined]
    return None


def exports_of(layer: str) -> dict[str, list[str]]:
    """Each module of ``layer`` -> its exported names (a name that is also a module's name is
    left out: once that module is imported the package attribute is the module)."""
    package = ROOT / "lidarcal_ros" / layer
    owner: dict[str, str] = {}
    for path in sorted(package.glob("*.py")):
        if path.name == "__init__.py":
            continue
        names = module_all(path)
        if names is None:
            sys.exit(f"update_exports: {path} has no __all__")
        for name in names:
            if (package / f"{name}.py").exists():
                continue
            if name in owner:
                sys.exit(f"update_exports: {name} in both {owner[name]} and {path.stem}")
            owner[name] = path.stem
    modules: dict[str, list[str]] = {}
    for name, module in owner.items():
        modules.setdefault(module, []).append(name)
    return modules


def table_lines(layer: str, modules: dict[str, list[str]]) -> list[str]:
    """The generated block: the table and the one call that exports it."""
    noqa = "  # noqa: E402 (after the DDS set-up)" if layer == "nodes" else ""
    lines = [MARK_BEGIN, "from lidarcal_ros.exports import lazy_exports" + noqa, "",
             "_EXPORTS = {"]
    for module in sorted(modules):
        body = ", ".join(f'"{n}"' for n in sorted(modules[module]))
        one = f'    "{module}": ({body}{"," if len(modules[module]) == 1 else ""}),'
        if len(one) <= 99:
            lines.append(one)
            continue
        lines.append(f'    "{module}": (')
        lines.extend(textwrap.wrap(body + ",", width=95, initial_indent="        ",
                                   subsequent_indent="        ", break_on_hyphens=False,
                                   break_long_words=False))
        lines.append("    ),")
    lines += ["}", "__getattr__, __dir__, __all__ = lazy_exports(__name__, _EXPORTS)", MARK_END]
    return lines


def main() -> None:
    for layer in sys.argv[1:] or LAYERS:
        init = ROOT / "lidarcal_ros" / layer / "__init__.py"
        text = init.read_text()
        if MARK_BEGIN in text:
            text = text[:text.index(MARK_BEGIN)]
        modules = exports_of(layer)
        init.write_text(text.rstrip("\n") + "\n\n" + "\n".join(table_lines(layer, modules))
                        + "\n")
        print(f"{layer}: {sum(map(len, modules.values()))} names from {len(modules)} modules")


if __name__ == "__main__":
    main()
