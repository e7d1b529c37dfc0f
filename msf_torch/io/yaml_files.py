"""Reading YAML config files: one loader for every config the project reads.

:func:`read_yaml` parses a file with :class:`ConfigLoader` and returns a
:class:`YamlDocument`: the data, the 1-based line of every key and list item, and the file.
Whatever is wrong with the file itself ends in a :class:`~msf_torch.io.errors.DataError`
naming it (and the line, when there is one): a path that is a folder or unreadable, a YAML
syntax error, a key given twice in one mapping (plain YAML would keep the last one without a
word).

:class:`ConfigLoader` is PyYAML's safe loader with the YAML 1.2 core schema's scalars, which
is what people write in configs and what ROS 2 (yaml-cpp) reads:

* ``1e-4``, ``5E+3`` and ``.5e-3`` are floats (YAML 1.1, PyYAML's default, wants a dot in
  the mantissa and a sign in the exponent, so ``1e-4`` would stay the string ``'1e-4'``);
* only ``true`` / ``false`` (any case) are booleans: ``on``, ``off``, ``yes``, ``no`` stay
  strings (``nhc: on`` means the string ``'on'``, not ``True``).
"""

from __future__ import annotations

__all__ = [
    "ConfigLoader",
    "YamlDocument",
    "did_you_mean",
    "line_map",
    "named_key",
    "read_yaml",
]

import difflib
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from msf_torch.io.errors import DataError


class ConfigLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` with YAML 1.2 core-schema floats and booleans (module docstring)."""


_BOOL_TAG = "tag:yaml.org,2002:bool"
_FLOAT_TAG = "tag:yaml.org,2002:float"
ConfigLoader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag not in (_BOOL_TAG, _FLOAT_TAG)]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
ConfigLoader.add_implicit_resolver(
    _BOOL_TAG, re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)
ConfigLoader.add_implicit_resolver(
    _FLOAT_TAG,
    re.compile(
        r"""^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
        |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+
        |[-+]?\.(?:inf|Inf|INF)
        |\.(?:nan|NaN|NAN))$""",
        re.X,
    ),
    list("-+0123456789."),
)


def did_you_mean(key: object, known: Iterable[str]) -> str:
    """`` (did you mean 'a' or 'b'?)`` naming the known keys closest to a misspelt one, or
    an empty string when none is close (``difflib`` ratio >= 0.6)."""
    close = difflib.get_close_matches(str(key), sorted(known), n=2, cutoff=0.6)
    return f" (did you mean {' or '.join(repr(k) for k in close)}?)" if close else ""


def named_key(message: object, keys: Iterable[str], prefix: str = "") -> str | None:
    """The first of ``keys`` that a validation message names as ``'<prefix><key>'`` (the
    config classes' wording), to locate the error at that key's line; None if none."""
    text = str(message)
    return next((k for k in keys if f"'{prefix}{k}'" in text), None)


def line_map(text: str) -> tuple[dict[tuple, int], list[tuple[tuple, int, int]]]:
    """Key path -> 1-based line of every key and list item of a YAML document, and the keys
    given twice in one mapping as ``(key path, line, line of the first)``. A document that
    does not parse gives empty results (:func:`read_yaml` reports the syntax error)."""
    lines: dict[tuple, int] = {}
    repeated: list[tuple[tuple, int, int]] = []
    try:
        root = yaml.compose(text, Loader=ConfigLoader)
    except yaml.YAMLError:
        return lines, repeated

    def walk(node, path: tuple) -> None:
        if isinstance(node, yaml.MappingNode):
            seen: dict[str, int] = {}
            for key, value in node.value:
                child = (*path, str(key.value))
                line = key.start_mark.line + 1
                if child[-1] in seen:
                    repeated.append((child, line, seen[child[-1]]))
                seen[child[-1]] = line
                lines[child] = line
                walk(value, child)
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                lines[(*path, i)] = item.start_mark.line + 1
                walk(item, (*path, i))

    if root is not None:
        walk(root, ())
    return lines, repeated


@dataclass
class YamlDocument:
    """A parsed YAML file.

    Attributes:
        path: the file.
        data: what it holds (None for an empty file).
        lines: key path (tuple of keys and list indices) -> 1-based line.
    """

    path: Path
    data: Any
    lines: dict[tuple, int] = field(default_factory=dict)

    def line_of(self, *keys: Any) -> int | None:
        """1-based line of the deepest known prefix of the key path, or None."""
        for cut in range(len(keys), 0, -1):
            if keys[:cut] in self.lines:
                return self.lines[keys[:cut]]
        return None

    def error(self, problem: str, *keys: Any) -> DataError:
        """A :class:`DataError` on this file at the line of ``keys`` (field = dotted path)."""
        dotted = ".".join(str(k) for k in keys) if keys else None
        return DataError(self.path, problem, line=self.line_of(*keys), field=dotted)


def read_yaml(path: str | os.PathLike[str], what: str = "config") -> YamlDocument:
    """Read and parse a YAML file with :class:`ConfigLoader`.

    Args:
        path: the file.
        what: what the file is meant to be, for messages (``"robot config"``, ...).
    Returns:
        the :class:`YamlDocument`.
    Raises:
        DataError: the path is missing, a folder or unreadable; the YAML does not parse
            (with the line); a key is given twice in one mapping (with both lines).
    """
    file = Path(path)
    if file.is_dir():
        raise DataError(file, f"is a folder; expected a YAML {what} file")
    try:
        text = file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(file, f"no such file (expected a YAML {what})") from None
    except (OSError, UnicodeDecodeError) as err:
        reason = getattr(err, "strerror", None) or str(err)
        raise DataError(file, f"cannot read the {what} ({reason})") from None
    try:
        data = yaml.load(text, Loader=ConfigLoader)  # noqa: S506 (a safe loader)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        problem = getattr(err, "problem", None) or str(err)
        raise DataError(
            file,
            f"not valid YAML ({problem})",
            line=None if mark is None else mark.line + 1,
        ) from None
    lines, repeated = line_map(text)
    if repeated:
        keys, line, first = repeated[0]
        raise DataError(
            file,
            f"given twice (also on line {first}); YAML would keep only the last",
            line=line,
            field=".".join(str(k) for k in keys),
        )
    return YamlDocument(file, data, lines)
