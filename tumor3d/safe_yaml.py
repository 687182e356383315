"""Safe YAML: the one parser of every YAML document the tool reads.

``yaml.SafeLoader`` semantics (no Python objects), plus what PyYAML does not
refuse by itself: alias bombs (more than ``YAML_MAX_ALIASES`` aliases, or more
than ``YAML_MAX_EXPANDED_NODES`` nodes once aliases are expanded), recursive
aliases, a key given twice in one mapping, and documents over
``YAML_MAX_BYTES`` characters (:mod:`tumor3d.constants`). Used by
:mod:`tumor3d.config` (``--config`` files) and the readers (``stack.yaml``).
"""

from __future__ import annotations

import re
from typing import Any

import yaml

from tumor3d.constants import YAML_MAX_ALIASES, YAML_MAX_BYTES, YAML_MAX_EXPANDED_NODES
from tumor3d.errors import ConfigError

__all__ = ["load_yaml", "yaml_reads_as_text"]


class _BoundedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses alias bombs before anything is constructed."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._aliases = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > YAML_MAX_ALIASES:
                event = self.peek_event()
                raise yaml.YAMLError(
                    f"more than {YAML_MAX_ALIASES} aliases (*name), refused as a possible "
                    f"alias bomb (line {event.start_mark.line + 1})"
                )
        return super().compose_node(parent, index)

    def compose_document(self) -> Any:
        node = super().compose_document()
        _check_expanded_size(node)
        _check_duplicate_keys(node)
        return node


def _check_duplicate_keys(root: Any) -> None:
    """Refuse a mapping that gives a key twice (YAML would silently keep the last)."""
    seen_nodes: set[int] = set()
    stack = [root]
    while stack:
        node = stack.pop()
        if id(node) in seen_nodes:
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict[str, int] = {}
            for key, _ in node.value:
                if isinstance(key, yaml.ScalarNode) and key.tag != "tag:yaml.org,2002:merge":
                    line = key.start_mark.line + 1
                    if key.value in first:
                        raise yaml.YAMLError(
                            f"the key '{key.value}' is given twice (lines {first[key.value]} "
                            f"and {line}); YAML would silently drop the first"
                        )
                    first[key.value] = line
        stack.extend(_children(node))


def _check_expanded_size(root: Any) -> None:
    """Refuse a node graph that expands to more than YAML_MAX_EXPANDED_NODES nodes."""
    sizes: dict[int, int] = {}
    stack: list[tuple[Any, bool]] = [(root, False)]
    on_path: set[int] = set()
    while stack:
        node, done = stack.pop()
        key = id(node)
        if done:
            on_path.discard(key)
            children = _children(node)
            total = 1 + sum(sizes[id(c)] for c in children)
            if total > YAML_MAX_EXPANDED_NODES:
                raise yaml.YAMLError(
                    f"the document expands to more than {YAML_MAX_EXPANDED_NODES:,} values "
                    "through its aliases, refused as a possible alias bomb"
                )
            sizes[key] = total
            continue
        if key in sizes:
            continue
        if key in on_path:
            raise yaml.YAMLError("a recursive alias (an anchor used inside itself)")
        on_path.add(key)
        stack.append((node, True))
        stack.extend((c, False) for c in _children(node) if id(c) not in sizes)


def _children(node: Any) -> list[Any]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    return []


def load_yaml(text: str, *, source: str = "<yaml>") -> Any:
    """Parse YAML text safely: no Python objects, no alias bombs, bounded size.

    Every YAML the tool reads (``--config`` files, ``stack.yaml``) goes
    through here: ``yaml.SafeLoader`` semantics, with at most
    ``YAML_MAX_ALIASES`` aliases, at most ``YAML_MAX_EXPANDED_NODES`` nodes
    once aliases are expanded, and at most ``YAML_MAX_BYTES`` characters
    (see :mod:`tumor3d.constants`).

    Parameters
    ----------
    text : str
        The document.
    source : str
        Where it came from, for the error message.

    Returns
    -------
    object
        The parsed document (``None`` for an empty one).

    Raises
    ------
    ConfigError
        On a syntax error or a refused document; one line naming ``source``.

    Examples
    --------
    >>> load_yaml("{a: &x [1, 2], b: *x}")
    {'a': [1, 2], 'b': [1, 2]}
    """
    if not isinstance(text, str):
        raise TypeError(f"YAML text must be a str, got {type(text).__name__}")
    if len(text) > YAML_MAX_BYTES:
        raise ConfigError(
            f"YAML document of {len(text):,} characters, more than the {YAML_MAX_BYTES:,} allowed",
            path=source,
        )
    loader = _BoundedLoader(text)
    try:
        return loader.get_single_data()
    except yaml.YAMLError as exc:
        text_of = " ".join(str(exc).split())  # one line
        if len(text_of) > 300:
            text_of = text_of[:297] + "..."
        raise ConfigError(f"not valid YAML: {text_of}", path=source) from None
    finally:
        loader.dispose()


def yaml_reads_as_text(value: str) -> bool:
    """True for a number in exponent form that YAML 1.1 (PyYAML) reads as text.

    ``1e1``, ``1e-3``, ``2.5E3``: YAML wants a point and a signed exponent (``1.0e+1``);
    ``'1.0e+1'`` arrives as text only when quoted.

    >>> [yaml_reads_as_text(v) for v in ("1e1", "1e-3", "2.5E3", "10", "abc", "1.0e+1")]
    [True, True, True, False, False, False]
    >>> yaml_reads_as_text("-.5e+3"), yaml_reads_as_text(".5e+3")  # YAML: text, a float
    (True, False)
    """
    try:
        float(value)
    except ValueError:
        return False
    # PyYAML's float: a sign only before digits ahead of the point, a point, a signed exponent
    yaml_float = re.fullmatch(r"[-+]?\d[\d_]*\.[\d_]*[eE][-+]\d+|\.\d[\d_]*[eE][-+]\d+", value)
    return "e" in value.lower() and "inf" not in value.lower() and yaml_float is None
