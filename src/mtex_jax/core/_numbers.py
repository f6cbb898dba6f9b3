"""The numbers of the text files the package reads (BVH, DeepMimic JSON, the salsa metadata,
keypoint and camera files, the metadata of model files): one rule for all of them (issue 57).

A number is a finite float64. A decimal no float holds (a 401-digit integer, ``1e400``) and
NaN or infinity in any spelling (``nan``, ``NaN``, ``INF``, ``-Infinity``; JSON's ``NaN`` and
``Infinity``) are a ``ValueError`` naming the file and the 1-based line, never an
``OverflowError`` or a NaN passed on (where a format gives NaN a meaning, the pixel of a missing
keypoint, :func:`load_json` reads it with ``nonfinite=True`` and the reader checks where it
is). A denormal (``4e-320``) is a finite float and is read as
its value (a reader's range checks then apply, e.g. to a frame time), a decimal below the
smallest denormal (``1e-400``) as zero, like ``-0.0``.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Iterator
from typing import Any

from ._limits import check_json_depth

__all__ = ["NUMBER", "json_value_line", "load_json", "number_problem", "show_token"]

#: A strict decimal number of a text file, ASCII digits only (no ``1_0``, ``inf``, ``nan``,
#: ``١`` or ``１``, which ``float`` accepts).
NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
# NaN and infinity as JSON does not spell them (where json.loads stops)
_NOT_JSON_NON_FINITE = re.compile(r"[+-]?(?:nan|inf(?:inity)?)(?![A-Za-z0-9])", re.IGNORECASE)
# the most digits an integer below float64's largest value (1.8e308) can have
_MAX_DIGITS = 309


def show_token(tok: str) -> str:
    """``repr(tok)``, shortened for a message when it is long (a 401-digit integer)."""
    if len(tok) <= 24:
        return repr(tok)
    return f"'{tok[:10]}...{tok[-6:]}' ({len(tok)} characters)"


def _too_large(tok: str, at: str) -> str:
    digits = tok.lstrip("+-")
    what = f"a {len(digits)}-digit integer" if digits.isdigit() else f"the number {show_token(tok)}"
    return f"{what}{at} is too large for a float"


def number_problem(tok: str, at: str = "") -> str | None:
    """Why the text token ``tok`` is not a number of a file, or ``None`` when it is a strict
    decimal of a finite float64 (denormals included).

    Args:
        tok: the token, e.g. ``"1.5e-3"``.
        at: words placed after the token in the message, e.g. ``" in frame 3"``.

    Returns:
        ``"non-finite value 'nan' in frame 3"``, ``"non-numeric token '1_0' in frame 3"`` or
        ``"a 401-digit integer in frame 3 is too large for a float"``; ``None`` for a number.
    """
    if _NON_FINITE.fullmatch(tok):
        return f"non-finite value {show_token(tok)}{at}"
    if not NUMBER.fullmatch(tok):
        return f"non-numeric token {show_token(tok)}{at}"
    if math.isinf(float(tok)):  # float() of a decimal overflows to inf, never raises
        return _too_large(tok, at)
    return None


class _Refused(Exception):
    """A JSON number refused by a parse hook (its line is found afterwards)."""


def _json_float(tok: str) -> float:
    v = float(tok)
    if math.isinf(v):
        raise _Refused(tok)
    return v


def _json_int(tok: str) -> int:
    # no int() of a long digit string: beyond 4300 digits Python refuses to convert it
    if len(tok.lstrip("-")) > _MAX_DIGITS or math.isinf(float(tok)):
        raise _Refused(tok)
    return int(tok)


def _json_refused_constant(tok: str) -> float:
    raise _Refused(tok)


def _json_problem(tok: str, nonfinite: bool) -> str | None:
    """Why a JSON number token is refused (``None``: it is read)."""
    if tok in ("NaN", "Infinity", "-Infinity"):
        if nonfinite:
            return None
        return f"non-finite value {tok} (NaN and Infinity are refused)"
    if math.isinf(float(tok)):
        return _too_large(tok, "")
    return None


# a JSON token: a string, a structural character, a number or a constant (true, false and null
# are skipped: they hold no digit)
_TOKEN = re.compile(r'"[^"\\]*(?:\\.[^"\\]*)*"|[{}\[\]:,]|-?Infinity|NaN|-?\d[\d.eE+-]*')


def _values(text: str) -> Iterator[tuple[tuple[str | int, ...], int, str]]:
    """``(path, line, token)`` of every value of JSON ``text`` in document order: its path
    of keys and indices, its 1-based line and its first token (``[`` or ``{`` for a container,
    a string, a number or a constant). Up to the first syntax error the document is assumed
    valid (it is scanned only after ``json.loads`` got that far)."""
    path: list[str | int] = []
    is_object: list[bool] = []
    expect_key = False
    line, pos = 1, 0
    for m in _TOKEN.finditer(text):
        line += text.count("\n", pos, m.start())
        pos = m.start()
        tok = m.group()
        c = tok[0]
        if c in "]}":
            if is_object:
                is_object.pop()
                path.pop()
            expect_key = False
        elif c == ",":
            if is_object and not is_object[-1]:
                path[-1] = int(path[-1]) + 1
            expect_key = bool(is_object) and is_object[-1]
        elif c == ":":
            expect_key = False
        elif expect_key:  # an object's key
            try:
                path[-1] = str(json.loads(tok))
            except ValueError:
                path[-1] = tok[1:-1]
            expect_key = False
        else:
            yield tuple(path), line, tok
            if c in "[{":
                is_object.append(c == "{")
                path.append("" if c == "{" else 0)
                expect_key = c == "{"


def _path_name(path: tuple[str | int, ...]) -> str:
    """``Frames[3][7]``, ``center[1]``, ``[0].keypoints[5]``."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p[:40]}" if out else p[:40])
    return out


def json_value_line(text: str, path: tuple[str | int, ...]) -> int | None:
    """The 1-based line where the value at ``path`` (keys and indices, e.g. ``("Frames",
    3)``) of JSON ``text`` starts, or ``None`` if there is none."""
    for p, line, _ in _values(text):
        if p == path:
            return line
    return None


def load_json(text: str, source: str, *, what: str | None = None, nonfinite: bool = False) -> Any:
    """``json.loads(text)`` with the rule of this module for numbers: an integer or a decimal no
    float64 holds (a 401-digit integer, ``1e400``, which ``json`` reads as inf) and,
    unless ``nonfinite``, the constants ``NaN``, ``Infinity`` and ``-Infinity`` are refused
    naming the line and the value's path; denormals and ``-0.0`` are read as they are.
    Integers are read as ``int``, decimals as ``float``, as ``json.loads`` does.

    Args:
        text: the JSON text.
        source: the file, for messages.
        what: the kind of file expected, e.g. ``"camera file"``: a syntax error then reads
            ``FILE:LINE: not a camera file: invalid JSON: ...``.
        nonfinite: read ``NaN`` and ``Infinity`` as floats (where a format allows them).

    Raises:
        ValueError: ``FILE:LINE: ...`` for a refused number or invalid JSON; JSON nested
            deeper than ``MAX_DEPTH`` (refused before parsing, without recursion).
    """
    check_json_depth(text, source)  # json.loads recurses: refuse deep nesting first
    constant: Callable[[str], float] = float if nonfinite else _json_refused_constant
    try:
        return json.loads(
            text, parse_float=_json_float, parse_int=_json_int, parse_constant=constant
        )
    except _Refused:
        for path, line, tok in _values(text):
            if tok[0] in "-0123456789IN" and (problem := _json_problem(tok, nonfinite)):
                at = f" {_path_name(path)}:" if path else ""
                raise ValueError(f"{source}:{line}:{at} {problem}") from None
        raise ValueError(f"{source}: a number no float holds") from None  # not reached
    except json.JSONDecodeError as e:
        kind = f" not a {what}:" if what else ""
        msg = e.msg
        if spelt := _NOT_JSON_NON_FINITE.match(text, e.pos):  # nan, inf, INF, -infinity ...
            msg = f"{spelt.group()!r} is not a JSON number"
        hint = " (truncated file?)" if e.pos >= len(text.rstrip()) else ""
        raise ValueError(
            f"{source}:{e.lineno}:{kind} invalid JSON: {msg} at column {e.colno}{hint}"
        ) from None
    except RecursionError:  # not reached: the depth is checked first
        raise ValueError(f"{source}: JSON nested too deeply") from None
