"""ODL (Object Description Language) text of HDF-EOS / ECS metadata attributes.

HDF-EOS2 products carry their metadata as ODL text in global attributes (``StructMetadata.0``,
``coremetadata.0``, ``productmetadata.0`` ...; ASTER notes §2.1)::

    GROUP = INVENTORYMETADATA
      OBJECT = SHORTNAME
        NUM_VAL = 1
        VALUE = "ASTL1A"
      END_OBJECT = SHORTNAME
    END_GROUP = INVENTORYMETADATA
    END

:func:`parse_odl` turns such text into nested dicts (a group or an object is a dict of its
entries; repeated names get ``.2``, ``.3`` suffixes), :func:`flatten_odl` gives the flat
``NAME[.CLASS] = VALUE`` view GDAL shows (and ``ADDITIONALATTRIBUTENAME`` /
``PARAMETERVALUE`` pairs as ``name = value``), :func:`format_odl` writes nested dicts back.
"""

from __future__ import annotations

import re

from stereodem.core.errors import InputError

_NUMBER = re.compile(r"^[+-]?(\d+\.?\d*|\.\d+)([eEdD][+-]?\d+)?$")


def _value(text: str):
    """One ODL value: quoted string, number, bare word, or a parenthesised tuple of those."""
    s = text.strip()
    if s.startswith("(") and s.endswith(")"):
        return tuple(_value(p) for p in _split_top(s[1:-1]))
    if len(s) >= 2 and s[0] == s[-1] == '"':
        return s[1:-1]
    if _NUMBER.match(s):
        num = s.replace("D", "E").replace("d", "e")
        try:
            return int(num)
        except ValueError:
            return float(num)
    return s


def _split_top(s: str):
    """Split a tuple body at commas outside quotes and nested parentheses."""
    parts, depth, quote, cur = [], 0, False, []
    for ch in s:
        if ch == '"':
            quote = not quote
        elif not quote and ch == "(":
            depth += 1
        elif not quote and ch == ")":
            depth -= 1
        if ch == "," and depth == 0 and not quote:
            parts.append("".join(cur))
            cur = []
        else:
            cur.append(ch)
    if "".join(cur).strip():
        parts.append("".join(cur))
    return parts


def _statements(text: str):
    """``(key, raw value)`` pairs; a value continues over lines until quotes and brackets close."""
    buf = ""
    for line in text.replace("\r", "").split("\n"):
        buf = f"{buf} {line.strip()}" if buf else line.strip()
        if not buf or buf.startswith("/*"):
            buf = ""
            continue
        if buf.count('"') % 2 or buf.count("(") > buf.count(")"):
            continue
        if buf == "END":
            return
        key, sep, val = buf.partition("=")
        buf = ""
        if sep:
            yield key.strip(), val.strip()


def parse_odl(text: str, *, source: str = "ODL") -> dict:
    """Parse ODL text into nested dicts (see the module docstring).

    Raises
    ------
    InputError
        Unbalanced ``GROUP``/``OBJECT`` ... ``END_*`` statements.
    """
    root: dict = {}
    stack = [("", root)]
    for key, raw in _statements(text):
        upper = key.upper()
        if upper in ("GROUP", "OBJECT"):
            name = str(_value(raw))
            node: dict = {}
            parent = stack[-1][1]
            slot, k = name, 2
            while slot in parent:
                slot, k = f"{name}.{k}", k + 1
            parent[slot] = node
            stack.append((name, node))
        elif upper in ("END_GROUP", "END_OBJECT"):
            if len(stack) == 1:
                raise InputError(f"{source}: {key} = {raw} without a matching opening statement")
            stack.pop()
        else:
            stack[-1][1][key] = _value(raw)
    if len(stack) != 1:
        raise InputError(f"{source}: ODL group/object {stack[-1][0]!r} is never closed")
    return root


def flatten_odl(tree: dict) -> dict:
    """GDAL's flat view: every object with a ``VALUE`` becomes ``NAME[.CLASS] = VALUE``."""
    flat: dict = {}

    def walk(node):
        pending_name = None
        for name, sub in node.items():
            if not isinstance(sub, dict):
                continue
            base = (
                name.split(".")[0]
                if re.search(r"\.\d+$", name) and name.rsplit(".", 1)[0] in node
                else name
            )
            if "VALUE" in sub:
                key = base + (f".{sub['CLASS']}" if "CLASS" in sub else "")
                if base.upper() == "ADDITIONALATTRIBUTENAME":
                    pending_name = sub["VALUE"]
                elif base.upper() == "PARAMETERVALUE" and pending_name is not None:
                    flat[str(pending_name)] = sub["VALUE"]
                    pending_name = None
                else:
                    flat[key] = sub["VALUE"]
            walk(sub)

    walk(tree)
    return flat


def format_odl(tree: dict, *, indent: int = 2) -> str:
    """ODL text from nested dicts: a dict holding ``VALUE`` is an OBJECT, others GROUPs."""
    lines: list[str] = []

    def fmt(v):
        if isinstance(v, str):
            return f'"{v}"'
        if isinstance(v, (tuple, list)):
            return "(" + ", ".join(fmt(x) for x in v) + ")"
        if isinstance(v, float):
            return repr(v)
        return str(v)

    def emit(node, depth):
        pad = " " * (indent * depth)
        for name, sub in node.items():
            if isinstance(sub, dict):
                kind = "OBJECT" if "VALUE" in sub else "GROUP"
                base = re.sub(r"\.\d+$", "", name) if kind == "OBJECT" else name
                lines.append(f"{pad}{kind} = {base}")
                emit(sub, depth + 1)
                lines.append(f"{pad}END_{kind} = {base}")
            else:
                lines.append(f"{pad}{name} = {fmt(sub)}")

    emit(tree, 0)
    lines.append("END")
    return "\n".join(lines) + "\n"
