"""YAML read with one-line errors and bounds a hostile file cannot get past."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lidarcal_ros.errors import ConfigError

#: Largest YAML file read, bytes (a calibration of a thousand strips' splines is a few MB).
MAX_YAML_BYTES = 64 * 1024 * 1024
#: Deepest nesting of collections (the tool's own files nest five deep).
MAX_YAML_DEPTH = 100
#: Most nodes a document may stand for with its aliases expanded: a few dozen nested aliases
#: (``*name``) stand for billions of nodes (the "billion laughs"), which every later walk
#: over the document would visit.
MAX_YAML_NODES = 10_000_000


class YamlBoundError(yaml.YAMLError):
    """A document beyond :data:`MAX_YAML_DEPTH` or :data:`MAX_YAML_NODES`."""


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses deep nesting and alias bombs as it composes."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._depth = 0
        self._expanded: dict[int, int] = {}  # id(node) -> nodes it stands for, expanded

    def compose_node(self, parent: Any, index: Any) -> Any:
        """PyYAML's node of the next event, counted against the bounds."""
        self._depth += 1
        if self._depth > MAX_YAML_DEPTH:
            raise YamlBoundError(f"nests deeper than {MAX_YAML_DEPTH} levels")
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if id(node) not in self._expanded:  # an alias's node is counted already
            children = (node.value if isinstance(node, yaml.SequenceNode) else
                        [n for pair in node.value for n in pair]
                        if isinstance(node, yaml.MappingNode) else [])
            size = 1 + sum(self._expanded.get(id(child), 1) for child in children)
            if size > MAX_YAML_NODES:
                raise YamlBoundError(f"stands for more than {MAX_YAML_NODES:,} nodes once its "
                                     "aliases are expanded (an alias bomb)")
            self._expanded[id(node)] = size
        return node


def load_yaml_text(text: str, *, source: str, what: str = "file") -> Any:
    """Parse YAML ``text`` (from ``source``, named in errors) within the bounds above.

    Raises
    ------
    ConfigError
        ``"<source>: <what> is not valid YAML at line N"`` or ``"<source>: <what> nests
        deeper than ..."`` / ``"... stands for more than ... nodes ..."``.
    """
    try:
        return yaml.load(text, Loader=_BoundedLoader)  # a SafeLoader: no Python tags
    except YamlBoundError as exc:
        raise ConfigError(f"{source}: {what} {exc}; refused") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{source}: {what} is not valid YAML{where}") from None


def read_yaml(path: str | Path, *, what: str = "file") -> Any:
    """Parse a YAML file within the bounds above.

    Raises
    ------
    ConfigError
        ``"<path>: cannot read <what> (<reason>)"``, ``"<path>: <what> is not text"``, one of
        :func:`load_yaml_text`'s, or a file over :data:`MAX_YAML_BYTES`.
    """
    path = Path(path)
    try:
        with path.open("rb") as handle:
            data = handle.read(MAX_YAML_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if len(data) > MAX_YAML_BYTES:
        raise ConfigError(f"{path}: {what} is larger than {MAX_YAML_BYTES // 2**20} MiB; "
                          "refused")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: {what} is not text") from None
    return load_yaml_text(text, source=str(path), what=what)


__all__ = ["MAX_YAML_BYTES", "MAX_YAML_DEPTH", "MAX_YAML_NODES", "YamlBoundError",
           "load_yaml_text", "read_yaml"]
