"""The HIERARCHY section of a BVH file, parsed iteratively (no recursion, so a deeply nested
file gets a clear error instead of a ``RecursionError``), within the joint and depth limits."""

from __future__ import annotations

from collections.abc import Iterator

from ..core import MAX_ABS_VALUE, MAX_DEPTH, MAX_JOINTS, NUMBER, number_problem, show_token
from ..motion import POSITION_CHANNELS, ROTATION_CHANNELS, Skeleton

__all__ = ["NUMBER", "Tokens", "parse_hierarchy"]

_CHANNEL_CANON = {c.lower(): c for c in ROTATION_CHANNELS + POSITION_CHANNELS}


class Tokens:
    """A stream of (token, line number) pairs with helpful errors."""

    def __init__(self, lines: list[str], source: str, stop: int) -> None:
        self.source = source
        self._it: Iterator[tuple[str, int]] = (
            (tok, i + 1) for i, line in enumerate(lines[:stop]) for tok in line.split()
        )
        self.last_line = max(stop, 1)

    def error(self, line: int, msg: str) -> ValueError:
        return ValueError(f"{self.source}:{line}: {msg}")

    def next(self, what: str) -> tuple[str, int]:
        try:
            return next(self._it)
        except StopIteration:
            raise self.error(
                self.last_line, f"unexpected end of hierarchy, expected {what}"
            ) from None

    def rest(self) -> tuple[str, int] | None:
        return next(self._it, None)

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok != word:
            raise self.error(line, f"expected {word!r}, found {tok!r}")
        return line

    def number(self, what: str) -> float:
        """The next token as a number (see :mod:`mtex_jax.core._numbers`: a strict decimal of
        a finite float, denormals read as they are), else an error naming the line."""
        tok, line = self.next(what)
        problem = number_problem(tok, f" for {what}")
        if problem is not None:
            raise self.error(line, problem)
        v = float(tok)
        if abs(v) > MAX_ABS_VALUE:
            raise self.error(
                line, f"value {show_token(tok)} for {what} exceeds {MAX_ABS_VALUE:g} in magnitude"
            )
        return v

    def offset(self) -> tuple[float, float, float]:
        return (self.number("OFFSET x"), self.number("OFFSET y"), self.number("OFFSET z"))

    def channels(self, name: str, line: int) -> tuple[str, ...]:
        n = self.number("channel count")
        if n != int(n) or not 0 <= n <= 6:
            raise self.error(line, f"invalid channel count {n:g} for joint {name!r}")
        chs: list[str] = []
        for _ in range(int(n)):
            c, cl = self.next("channel name")
            canon = _CHANNEL_CANON.get(c.lower())
            if canon is None:
                raise self.error(cl, f"unknown channel {c!r} for joint {name!r}")
            if canon in chs:
                raise self.error(cl, f"repeated channel {c!r} for joint {name!r}")
            chs.append(canon)
        return tuple(chs)


def parse_hierarchy(toks: Tokens) -> Skeleton:
    """Read ``HIERARCHY ROOT name { ... }`` from ``toks`` into a :class:`Skeleton`.

    Joints are kept on an explicit stack; more than :data:`~mtex_jax.core.MAX_JOINTS` joints
    or a nesting deeper than :data:`~mtex_jax.core.MAX_DEPTH` is a ``ValueError`` naming the
    line.
    """
    names: list[str] = []
    parents: list[int] = []
    offsets: list[tuple[float, float, float]] = []
    channels: list[tuple[str, ...]] = []
    end_sites: list[tuple[int, tuple[float, float, float]]] = []
    declared: list[int] = []  # line of each joint's name
    has_offset: list[bool] = []
    stack: list[int] = []

    def open_joint(name: str, parent: int, line: int) -> None:
        if len(names) >= MAX_JOINTS:
            raise toks.error(line, f"more than {MAX_JOINTS} joints (limit)")
        if len(stack) >= MAX_DEPTH:
            raise toks.error(line, f"joints nested more than {MAX_DEPTH} levels deep (limit)")
        stack.append(len(names))
        names.append(name)
        parents.append(parent)
        offsets.append((0.0, 0.0, 0.0))
        channels.append(())
        declared.append(line)
        has_offset.append(False)
        toks.expect("{")

    toks.expect("HIERARCHY")
    tok, ln = toks.next("'ROOT'")
    if tok != "ROOT":
        raise toks.error(ln, f"expected 'ROOT', found {tok!r}")
    root_name, ln = toks.next("root name")
    open_joint(root_name, -1, ln)
    while stack:
        idx = stack[-1]
        name = names[idx]
        tok, ln = toks.next("'}'")
        if tok == "}":
            if not has_offset[idx]:
                raise toks.error(declared[idx], f"joint {name!r} has no OFFSET")
            stack.pop()
        elif tok == "OFFSET":
            offsets[idx] = toks.offset()
            has_offset[idx] = True
        elif tok == "CHANNELS":
            channels[idx] = toks.channels(name, ln)
        elif tok == "JOINT":
            child, cl = toks.next("joint name")
            open_joint(child, idx, cl)
        elif tok == "End":
            toks.expect("Site")
            toks.expect("{")
            toks.expect("OFFSET")
            end_sites.append((idx, toks.offset()))
            toks.expect("}")
        else:
            raise toks.error(ln, f"unknown keyword {tok!r} in joint {name!r}")
    extra = toks.rest()
    if extra is not None:
        raise toks.error(extra[1], f"unexpected {extra[0]!r} after the root joint (one ROOT only)")
    try:
        return Skeleton(
            tuple(names), tuple(parents), tuple(offsets), tuple(channels), tuple(end_sites)
        )
    except ValueError as e:
        raise ValueError(f"{toks.source}: invalid skeleton: {e}") from None
