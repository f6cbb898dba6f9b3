"""BVH reader and writer (any channel order and Euler order per joint, end sites)."""

from __future__ import annotations

import itertools
import os
import re
import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ..core import (
    MAX_ABS_VALUE,
    MAX_FRAMES,
    atomic_write,
    check_count,
    check_frame_time,
    number_problem,
    read_input,
    show_token,
)
from ..motion import Motion, Skeleton
from ._bvh_hierarchy import Tokens, parse_hierarchy

__all__ = ["euler_to_quat", "parse_bvh", "quat_to_euler", "read_bvh", "write_bvh"]

_AXIS = {"X": 0, "Y": 1, "Z": 2}
# a character that no decimal number of a frame line holds (Python's float() also reads
# "1_0", "inf", "nan" and "infinity"; a BVH number is digits, sign, point and exponent only)
_NOT_NUMERIC = re.compile(r"[^0-9eE+\-.\s]")


def parse_bvh(text: str, source: str = "<string>", *, max_frames: int = MAX_FRAMES) -> Motion:
    """Parse BVH text into a :class:`Motion` (see :func:`read_bvh`); a leading UTF-8
    byte-order mark is skipped."""
    lines = text.removeprefix("\ufeff").splitlines()
    motion_line = next((i for i, ln in enumerate(lines) if ln.strip().upper() == "MOTION"), None)
    if motion_line is None:
        raise ValueError(f"{source}:{len(lines)}: no MOTION section (file truncated?)")
    skeleton = parse_hierarchy(Tokens(lines, source, motion_line))

    # --- MOTION section ---------------------------------------------------------------
    i = motion_line + 1
    n_frames, i = _header_value(lines, i, "Frames:", source, integer=True)
    frame_time, i = _header_value(lines, i, "Frame Time:", source, integer=False)
    if n_frames <= 0:
        raise ValueError(f"{source}:{i - 1}: zero frames (Frames: {int(n_frames)})")
    if n_frames > max_frames:
        raise ValueError(
            f"{source}:{i - 1}: Frames: {n_frames:.0f} exceeds the limit of {max_frames:,} frames"
        )
    if not frame_time > 0:
        raise ValueError(f"{source}:{i}: Frame Time must be positive, got {frame_time:g}")
    check_frame_time(frame_time, f"{source}:{i}")
    n_frames = int(n_frames)
    data = lines[i : i + n_frames]
    # trailing blank lines are fine; anything else after the frames is an error
    tail = [k for k, ln in enumerate(lines[i + n_frames :]) if ln.strip()]
    if tail:
        raise ValueError(
            f"{source}:{i + n_frames + tail[0] + 1}: more frame lines than 'Frames: {n_frames}'"
        )
    nc = skeleton.n_channels
    for k, ln in enumerate(data):
        bad = _NOT_NUMERIC.search(ln)
        if bad is not None:
            tok = next(t for t in ln.split() if bad.group() in t)
            problem = number_problem(tok, f" in frame {k}")
            raise ValueError(f"{source}:{i + k + 1}: {problem or f'non-numeric token {tok!r}'}")
    toks_per_line = [ln.split() for ln in data]
    for k, tl in enumerate(toks_per_line):
        if len(tl) != nc:
            raise ValueError(
                f"{source}:{i + k + 1}: frame {k} has {len(tl)} values, expected {nc} "
                f"(sum of CHANNELS)"
            )
    if len(data) < n_frames:
        raise ValueError(
            f"{source}:{len(lines)}: file truncated: 'Frames: {n_frames}' but only "
            f"{len(data)} frame lines"
        )
    try:
        values = np.array(list(itertools.chain.from_iterable(toks_per_line)), dtype=np.float64)
    except ValueError:  # a token such as "1e" or "." (only number characters got here)
        values = None
    if values is None or not np.isfinite(values).all():  # 1e400, or 400 digits: inf
        # name the first token that is no strict decimal of a finite float
        start = 0 if values is None else int(np.argmin(np.isfinite(values))) // max(nc, 1)
        for k in range(start, n_frames):
            for t in toks_per_line[k]:
                if (problem := number_problem(t, f" in frame {k}")) is not None:
                    raise ValueError(f"{source}:{i + k + 1}: {problem}")
        raise ValueError(f"{source}:{i + 1}: non-numeric frame values")  # not reached
    values = values.reshape(n_frames, nc)
    big = np.abs(values) > MAX_ABS_VALUE
    if big.any():
        k = int(np.nonzero(big.any(axis=1))[0][0])
        raise ValueError(
            f"{source}:{i + k + 1}: value in frame {k} exceeds {MAX_ABS_VALUE:g} in magnitude"
        )
    fps = 1.0 / frame_time
    if abs(fps - round(fps)) < 1e-4 * fps:
        fps = float(round(fps))
    return channels_to_motion(skeleton, values, fps)


def _header_value(
    lines: list[str], i: int, key: str, source: str, *, integer: bool
) -> tuple[float, int]:
    while i < len(lines) and not lines[i].strip():
        i += 1
    if i >= len(lines):
        raise ValueError(f"{source}:{len(lines)}: file truncated, expected {key!r}")
    ln = lines[i].strip()
    if not ln.startswith(key):
        raise ValueError(f"{source}:{i + 1}: expected {key!r}, found {ln[:40]!r}")
    rest = ln[len(key) :].strip()
    problem = number_problem(rest)
    if problem is not None:
        raise ValueError(
            f"{source}:{i + 1}: invalid value {show_token(rest)} for {key!r}: {problem}"
        )
    v = float(rest)
    if integer and v != int(v):
        raise ValueError(f"{source}:{i + 1}: invalid value {show_token(rest)} for {key!r}")
    return v, i + 1


def euler_to_quat(order: str, angles_deg: np.ndarray) -> np.ndarray:
    """Intrinsic Euler angles (degrees, BVH convention) to quaternions ``(w, x, y, z)``.

    ``order = "ZXY"`` means ``R = Rz(a0) @ Rx(a1) @ Ry(a2)``. ``angles_deg`` is
    ``(..., len(order))``; an empty order gives the identity.
    """
    angles_deg = np.asarray(angles_deg, dtype=np.float64)
    batch = angles_deg.shape[:-1]
    if not order:
        q = np.zeros((*batch, 4))
        q[..., 0] = 1.0
        return q
    rot = Rotation.from_euler(order.upper(), angles_deg.reshape(-1, len(order)), degrees=True)
    xyzw = rot.as_quat()
    return np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=-1).reshape(*batch, 4)


def quat_to_euler(order: str, q: np.ndarray) -> np.ndarray:
    """Quaternions ``(w, x, y, z)`` to intrinsic Euler angles in degrees, ``(..., len(order))``.

    For one axis the twist about that axis is returned; for two axes ``A, B`` the angles solve
    ``R e_B = R_A(a) e_B`` and ``Rᵀ e_A = R_B(−b) e_A`` (exact when the rotation is representable
    by those channels, a projection otherwise).
    """
    q = np.asarray(q, dtype=np.float64)
    batch = q.shape[:-1]
    n = len(order)
    if n == 0:
        return np.zeros((*batch, 0))
    flat = q.reshape(-1, 4)
    if n == 1:
        ax = _AXIS[order.upper()]
        ang = 2.0 * np.arctan2(flat[:, 1 + ax], flat[:, 0])
        ang = (ang + np.pi) % (2 * np.pi) - np.pi
        return np.degrees(ang).reshape(*batch, 1)
    rot = Rotation.from_quat(np.concatenate([flat[:, 1:], flat[:, :1]], axis=-1))
    if n == 2:
        # R = R_A(a) R_B(b): R e_B = R_A(a) e_B and Rᵀ e_A = R_B(−b) e_A give a and b in closed
        # form (the best fit when R is not representable by the two channels).
        ea = np.eye(3)[_AXIS[order[0].upper()]]
        eb = np.eye(3)[_AXIS[order[1].upper()]]
        eab = np.cross(ea, eb)
        mat = rot.as_matrix()
        v = mat @ eb
        w = np.einsum("nji,j->ni", mat, ea)
        a = np.arctan2(v @ eab, v @ eb)
        b = np.arctan2(w @ eab, w @ ea)
        return np.degrees(np.stack([a, b], axis=-1)).reshape(*batch, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        eul = rot.as_euler(order.upper(), degrees=True)
    return eul.reshape(*batch, 3)


def channels_to_motion(skeleton: Skeleton, values: np.ndarray, fps: float) -> Motion:
    """Turn a ``(T, n_channels)`` table of BVH channel values into a :class:`Motion`."""
    t = values.shape[0]
    j = skeleton.n_joints
    rot = np.zeros((t, j, 4))
    off = skeleton.offsets_array
    pos = np.broadcast_to(off, (t, j, 3)).copy()
    col = 0
    by_order: dict[str, list[tuple[int, list[int]]]] = {}
    has_nonroot_pos = False
    for ji, chs in enumerate(skeleton.channels):
        rcols: list[int] = []
        order = ""
        for c in chs:
            if c.endswith("position"):
                pos[:, ji, _AXIS[c[0]]] = values[:, col]
                if ji > 0:
                    has_nonroot_pos = True
            else:
                rcols.append(col)
                order += c[0]
            col += 1
        by_order.setdefault(order, []).append((ji, rcols))
    for order, items in by_order.items():
        idx = [ji for ji, _ in items]
        cols = np.asarray([rc for _, rc in items], dtype=np.int64).reshape(len(items), len(order))
        ang = values[:, cols]  # (T, G, n)
        rot[:, idx] = euler_to_quat(order, ang)
    local = pos if has_nonroot_pos else None
    return Motion(skeleton, float(fps), pos[:, 0].copy(), rot, local)


def motion_to_channels(motion: Motion) -> np.ndarray:
    """Inverse of :func:`channels_to_motion`: a ``(T, n_channels)`` table in file order."""
    m = motion.numpy()
    sk = m.skeleton
    t = m.n_frames
    out = np.zeros((t, sk.n_channels))
    col = 0
    euler_cache: dict[int, np.ndarray] = {}
    # group joints by order for vectorised conversion
    by_order: dict[str, list[int]] = {}
    for ji in range(sk.n_joints):
        by_order.setdefault(sk.rotation_order(ji), []).append(ji)
    for order, idx in by_order.items():
        e = quat_to_euler(order, np.asarray(m.rotations)[:, idx])
        for k, ji in enumerate(idx):
            euler_cache[ji] = e[:, k]
    for ji, chs in enumerate(sk.channels):
        r = 0
        for c in chs:
            if c.endswith("position"):
                if ji == 0:
                    src = np.asarray(m.root_positions)
                elif m.local_positions is not None:
                    src = np.asarray(m.local_positions)[:, ji]
                else:
                    src = np.broadcast_to(sk.offsets_array[ji], (t, 3))
                out[:, col] = src[:, _AXIS[c[0]]]
            else:
                out[:, col] = euler_cache[ji][:, r]
                r += 1
            col += 1
    return out


def read_bvh(path: str | os.PathLike[str], *, max_frames: int = MAX_FRAMES) -> Motion:
    """Read a BVH file.

    Every joint may have any subset of the six channels in any order; the rotation channels'
    order is the intrinsic Euler order (``Zrotation Xrotation Yrotation`` → ``Rz Rx Ry``).
    Position channels replace the corresponding component of the joint's OFFSET (for the
    root they are the root position). ``End Site`` entries are kept in
    ``skeleton.end_sites``. The frame rate is ``1 / Frame Time``, snapped to the nearest
    integer when within 0.01 % of it.

    Raises:
        ValueError: on malformed input, naming the file and line (truncated file, wrong number
            of values on a frame line, non-numeric or non-finite token, unknown keyword or
            channel, zero frames, invalid frame time; numbers are strict decimals: ``1_0``,
            ``inf``, ``nan`` and ``Infinity`` in any case are refused, and so is a decimal no
            float64 holds, a 401-digit integer or ``1e400``; a denormal, ``4e-320``, is read
            as its value and ``-0.0`` as zero, wherever a number goes: OFFSET, CHANNELS,
            ``Frames:``, ``Frame Time:``, frame lines) and on input beyond the limits of
            :mod:`mtex_jax.core` (a file larger than ``MAX_INPUT_BYTES`` or not a regular file,
            more than ``max_frames`` frames or ``MAX_JOINTS`` joints,
            joints nested deeper than ``MAX_DEPTH``, a frame time outside
            ``[MIN_FRAME_TIME, MAX_FRAME_TIME]``, a number beyond ``MAX_ABS_VALUE``).
    """
    p = Path(path)
    text = read_input(p, "BVH file").decode("utf-8", errors="replace")
    return parse_bvh(text, str(p), max_frames=max_frames)


def _dfs_order(sk: Skeleton) -> list[int]:
    children: dict[int, list[int]] = {i: [] for i in range(sk.n_joints)}
    for i, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(i)
    order: list[int] = []
    stack = [0]
    while stack:
        i = stack.pop()
        order.append(i)
        stack.extend(reversed(children[i]))
    return order


def write_bvh(path: str | os.PathLike[str], motion: Motion, *, precision: int = 6) -> None:
    """Write a motion as BVH with the skeleton's channels and Euler orders.

    Joints are written depth-first (children in index order), so a skeleton whose joints are
    already in depth-first order (every skeleton read from BVH) reads back in the same order.
    Frame values (Euler angles in degrees, positions in file units) are written with
    ``precision`` decimals; offsets are written exactly. The file is replaced atomically (a
    failed write leaves the previous file intact).
    """
    write_bvh_chunks(path, [motion], motion.n_frames, precision=precision)


def write_bvh_chunks(
    path: str | os.PathLike[str],
    motions: Iterable[Motion],
    n_frames: int,
    *,
    precision: int = 6,
) -> None:
    """Write one motion given as consecutive pieces as one BVH file, a piece at a time.

    As :func:`write_bvh` (which is this with one piece), for motions longer than memory holds
    (``mtex synth`` of a million frames, :func:`~mtex_jax.texture.synthesize_chunks`): the
    header is written from the first piece, then each piece's frames; only one piece is
    held. Every piece must have the first one's skeleton and frame rate, and the pieces
    together ``n_frames`` frames (the ``Frames:`` line comes first). The file is replaced
    atomically: if a piece is refused or the pieces are too few or too many, nothing is
    written.

    Raises:
        ValueError: a piece on another skeleton or frame rate, or not ``n_frames`` frames in
            all.
    """
    n_frames = check_count(n_frames, "write_bvh: n_frames", "MAX_FRAMES")
    pieces = iter(motions)
    try:
        first = next(pieces)
    except StopIteration:
        raise ValueError("write_bvh: no motion to write") from None
    sk = first.skeleton
    order = _dfs_order(sk)
    children: dict[int, list[int]] = {i: [] for i in range(sk.n_joints)}
    for i, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(i)
    ends: dict[int, list[tuple[float, float, float]]] = {}
    for p, o in sk.end_sites:
        ends.setdefault(p, []).append(o)
    fmt = f"%.{precision}f"
    out: list[str] = ["HIERARCHY"]

    def vec(o: tuple[float, float, float] | np.ndarray) -> str:
        return " ".join(repr(float(x)) for x in o)  # offsets exactly (shortest round trip)

    # depth-first without recursion: ("open", joint, depth) writes a joint's head and queues
    # its children, end sites and closing brace
    stack: list[tuple[str, int, int]] = [("open", 0, 0)]
    while stack:
        what, ji, depth = stack.pop()
        ind = "\t" * depth
        if what == "close":
            for o in ends.get(ji, []):
                out.append(f"{ind}\tEnd Site")
                out.append(f"{ind}\t{{")
                out.append(f"{ind}\t\tOFFSET {vec(o)}")
                out.append(f"{ind}\t}}")
            out.append(f"{ind}}}")
            continue
        kw = "ROOT" if ji == 0 else "JOINT"
        out.append(f"{ind}{kw} {sk.names[ji]}")
        out.append(f"{ind}{{")
        out.append(f"{ind}\tOFFSET {vec(sk.offsets[ji])}")
        if sk.channels[ji] or ji == 0:
            out.append(
                f"{ind}\tCHANNELS {len(sk.channels[ji])} {' '.join(sk.channels[ji])}".rstrip()
            )
        stack.append(("close", ji, depth))
        stack.extend(("open", c, depth + 1) for c in reversed(children[ji]))

    # reorder columns to the depth-first joint order
    starts = np.cumsum([0] + [len(c) for c in sk.channels])
    cols = np.concatenate(
        [np.arange(starts[j], starts[j + 1]) for j in order] or [np.zeros(0, np.int64)]
    ).astype(np.int64)
    out.append("MOTION")
    out.append(f"Frames: {n_frames}")
    out.append(f"Frame Time: {1.0 / first.fps:.10g}")
    row_fmt = " ".join([fmt] * cols.size)
    written = 0
    with atomic_write(path, "w", encoding="utf-8") as fh:
        fh.write("\n".join(out) + "\n")
        for m in itertools.chain([first], pieces):
            if m is not first and (m.skeleton != sk or m.fps != first.fps):
                raise ValueError(
                    f"write_bvh: piece at frame {written} has another skeleton or frame rate "
                    "than the first piece"
                )
            written += m.n_frames
            if written > n_frames:
                raise ValueError(f"write_bvh: the pieces have more than n_frames = {n_frames}")
            if cols.size:
                table = motion_to_channels(m)[:, cols]
                fh.write("\n".join(row_fmt % tuple(r) for r in table) + "\n")
        if written != n_frames:
            raise ValueError(f"write_bvh: the pieces have {written} frames, not {n_frames}")
        if not cols.size:  # no channels: the frame lines are empty (as they always were)
            fh.write("\n")
