r"""Read untrusted YAML safely: bounded size after alias expansion, no duplicate keys.

A few lines of YAML can describe billions of values through aliases (``&a [*b, *b,
...]``, the "billion laughs"): PyYAML shares the aliased objects, but validating or
printing them expands the tree. :func:`load_yaml` composes the document, counts the
nodes it stands for *with aliases expanded* (memoised, so the count itself is cheap),
refuses more than :data:`MAX_NODES`, recursive aliases and nesting deeper than
:data:`MAX_DEPTH`, reports duplicate mapping keys with their lines, and only then
constructs the Python objects (``yaml.SafeLoader``: no tags that run code). Control
characters are refused with their line: raw ones anywhere (the YAML reader's own rule),
escaped ones (``"lev\x07els"``) in keys, and NUL bytes in any value (no file name or
plugin key holds one).
"""

from __future__ import annotations

from typing import Any

import yaml

from .errors import SpecError

__all__ = ["MAX_NODES", "MAX_DEPTH", "load_yaml", "control_character"]

MAX_NODES = 10_000
"""Most YAML nodes a spec (or a ``--set`` value) may expand to; real specs have < 200."""
MAX_DEPTH = 50
"""Deepest nesting of sequences and mappings accepted."""


def load_yaml(text: str, origin: str) -> tuple[Any, yaml.Node | None]:
    """Parse ``text`` as one YAML document after checking its expanded size and keys.

    Args:
        text: the YAML text.
        origin: what to name in messages (a file name or ``--set 'a.b=...'``).

    Returns:
        ``(data, node)``: the Python value (None for an empty document) and the composed
        node graph (for line numbers), or ``(None, None)``.

    Raises:
        SpecError: invalid YAML (with its line), more than :data:`MAX_NODES` nodes after
            alias expansion, a recursive alias, nesting deeper than :data:`MAX_DEPTH`, or
            duplicate keys in a mapping (each with its line); one line per problem.
    """
    try:  # the reader checks the characters as soon as it is made
        loader = yaml.SafeLoader(text)
    except yaml.reader.ReaderError as exc:
        raise SpecError(_reader_error(exc, text, origin)) from None
    try:
        node = loader.get_single_node()
        if node is None:
            return None, None
        _check(node, origin)
        return loader.construct_document(node), node
    except yaml.reader.ReaderError as exc:  # a bad character further on (the reader reads in chunks)
        raise SpecError(_reader_error(exc, text, origin)) from None
    except (yaml.YAMLError, ValueError) as exc:  # ValueError: e.g. an integer of 100k digits
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark else ""
        problem = " ".join(str(getattr(exc, "problem", None) or exc).split())[:200]
        raise SpecError(f"{origin}:{where} not valid YAML: {problem}") from None
    except RecursionError:
        raise SpecError(f"{origin}: YAML nested too deeply (more than {MAX_DEPTH} levels)") from None
    finally:
        loader.dispose()


def control_character(text: str, allowed: str = "") -> str | None:
    """The first control character of ``text`` (Unicode category Cc) not in ``allowed``, or None."""
    for char in text:
        if (char < " " or "\x7f" <= char <= "\x9f") and char not in allowed:
            return char
    return None


def _reader_error(exc: yaml.reader.ReaderError, text: str, origin: str) -> str:
    """One line for the YAML reader's refusal of a character: its line, code point and column."""
    position = max(0, min(int(exc.position), len(text)))
    line = text.count("\n", 0, position) + 1
    column = position - (text.rfind("\n", 0, position) + 1) + 1
    what = "a NUL byte" if exc.character == 0 else f"control character U+{int(exc.character):04X}"
    return f"{origin}: line {line}: {what} at column {column}; a spec holds only printable text"


def _check(root: yaml.Node, origin: str) -> None:
    sizes: dict[int, int | None] = {}
    duplicates: list[str] = []

    def size(node: yaml.Node, depth: int) -> int:
        key = id(node)
        if key in sizes:
            if sizes[key] is None:
                raise SpecError(f"{origin}: line {node.start_mark.line + 1}: recursive YAML alias")
            return sizes[key]  # type: ignore[return-value]
        if depth > MAX_DEPTH:
            raise SpecError(f"{origin}: line {node.start_mark.line + 1}: YAML nested deeper than "
                            f"{MAX_DEPTH} levels")
        sizes[key] = None
        total = 1
        if isinstance(node, yaml.ScalarNode) and "\x00" in str(node.value):
            raise SpecError(f"{origin}: line {node.start_mark.line + 1}: a NUL character in the value "
                            f"{str(node.value)[:60]!r}; no spec value holds one")
        if isinstance(node, yaml.SequenceNode):
            total += sum(size(child, depth + 1) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            seen: dict[str, int] = {}
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    line = k.start_mark.line + 1
                    bad = control_character(str(k.value))
                    if bad is not None:
                        raise SpecError(f"{origin}: line {line}: key {k.value[:60]!r} contains control character "
                                        f"U+{ord(bad):04X}; keys are field and stage names")
                    if k.value in seen and k.value != "<<":
                        duplicates.append(f"line {line}: duplicate key {k.value[:60]!r} "
                                          f"(first on line {seen[k.value]})")
                    seen.setdefault(k.value, line)
                total += size(k, depth + 1) + size(v, depth + 1)
        if total > MAX_NODES:
            raise SpecError(f"{origin}: line {node.start_mark.line + 1}: the YAML expands to more than "
                            f"{MAX_NODES} values (aliases repeated?); a spec needs far fewer")
        sizes[key] = total
        return total

    size(root, 0)
    if duplicates:
        if len(duplicates) == 1:
            raise SpecError(f"{origin}: {duplicates[0]}")
        raise SpecError(f"{origin}: {len(duplicates)} duplicate keys\n  " + "\n  ".join(duplicates[:20]))
