"""Fuzzing the readers and the model files (issue 20): mutated real BVH (CMU salsa, cut to a
few frames), DeepMimic JSON and model files (a small texture and a feature map): truncated,
bytes flipped, inserted or repeated, numbers and counts changed, nested, headers inflated.
Every read either succeeds with finite data or raises ``ValueError``: never another
exception, never NaN; and, in a subprocess under ``RLIMIT_AS``, never more than a fixed
memory budget.

The default run reads more than 2,000 mutated inputs (the count is printed by the last test);
``pytest -m slow tests/test_fuzz.py`` reads more than 50,000.
"""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import textwrap
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

import mtex_jax as mj
from mtex_jax.texture import MotionTexture, Texton
from paper_settings import UNTIED

DATA = Path(mj.__file__).resolve().parent / "data" / "deepmimic"
COUNTS: dict[str, int] = {}
STARTED: list[float] = []  # when the first fuzz test of this run started

# ---------------------------------------------------------------------------------------------
# seeds: small real inputs
# ---------------------------------------------------------------------------------------------


def cut_bvh(text: str, n_frames: int = 3) -> str:
    lines = text.splitlines()
    m = next(i for i, ln in enumerate(lines) if ln.strip() == "MOTION")
    ft = next(ln for ln in lines[m:] if ln.strip().startswith("Frame Time"))
    frames = [ln for ln in lines[m + 1 :] if ln.strip() and ln.strip()[0] in "-0123456789."]
    return "\n".join([*lines[: m + 1], f"Frames: {n_frames}", ft, *frames[:n_frames]]) + "\n"


def cut_deepmimic(text: str, n_frames: int = 5) -> str:
    doc = json.loads(text)
    doc["Frames"] = doc["Frames"][:n_frames]
    return json.dumps(doc, indent=1)


@pytest.fixture(scope="module")
def seeds(cmu_files, tmp_path_factory) -> dict[str, bytes]:
    folder = tmp_path_factory.mktemp("fuzz")
    bvh = cut_bvh(Path(cmu_files[0]).read_text())
    mj.io.parse_bvh(bvh, "seed.bvh")
    dm = cut_deepmimic((DATA / "humanoid3d_dance_a.txt").read_text())
    mj.io.parse_deepmimic(dm, "seed.txt")
    clip = mj.load_example("dance_a")[:40]
    fm = mj.FeatureMap.fit([clip])
    fm.save(folder / "fm.npz")
    texture_file(fm, folder / "tex.npz", clip)
    return {
        "bvh": bvh.encode(),
        "deepmimic": dm.encode(),
        "feature_map": (folder / "fm.npz").read_bytes(),
        "texture": (folder / "tex.npz").read_bytes(),
    }


def texture_file(fm: mj.FeatureMap, path: Path, clip: mj.Motion) -> None:
    """A hand-made two-texton texture (no learning: the fuzz tests stay fast), carrying the
    contact model of ``clip`` (as a learned one does)."""
    rng = np.random.default_rng(0)
    D, k, n = len(fm.active), 2, 2

    def texton() -> Texton:
        C = np.linalg.qr(rng.standard_normal((D, k)))[0]
        return Texton(
            mu=jnp.asarray(rng.standard_normal(D)),
            C=jnp.asarray(C),
            A1=0.5 * jnp.eye(k),
            A2=0.1 * jnp.eye(k),
            d=jnp.zeros(k),
            B=0.2 * jnp.eye(k),
            sigma2=jnp.asarray(0.01),
            m0=jnp.zeros(2 * k),
            S0=jnp.eye(2 * k),
        )

    t = [texton() for _ in range(n)]
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *t)
    tex = MotionTexture(
        textons=stacked,
        M=jnp.asarray([[0.2, 0.8], [0.6, 0.4]]),
        pi=jnp.asarray([0.5, 0.5]),
        key_poses=jnp.asarray(rng.standard_normal((2, 2, D))),
        key_pose_labels=jnp.asarray([0, 1]),
        segment_lengths=jnp.asarray([10, 12]),
        segments=jnp.asarray([[0, 0, 10, 0], [0, 10, 12, 1]]),
        history=jnp.zeros((1, 2)),
        feature_map=fm,
        config=mj.LearnConfig(tmin=5, tmax=20, state_dim=k, **UNTIED),
        threshold=0.3,
        contacts=mj.motion.fit_contacts([clip], fps=fm.fps),
    )
    tex.save(path)
    mj.load_texture(path)


# ---------------------------------------------------------------------------------------------
# mutations
# ---------------------------------------------------------------------------------------------
NUMBERS = st.one_of(
    st.sampled_from(
        [
            "0",
            "-0",
            "1e-300",
            "1e300",
            "-1e300",
            "nan",
            "inf",
            "-inf",
            "1e6",
            "1e9",
            "-1",
            "99999999999999999999",
            "1e-9",
            "0.0",
            "3",
            "",
            "x",
            "1e",
            "--1",
            "0x10",
            "1_0",
        ]
    ),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-(10**12), 10**12).map(str),
)
_NUM = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@st.composite
def mutate(draw, data: bytes) -> bytes:
    """One to three random edits of ``data``."""
    for _ in range(draw(st.integers(1, 3))):
        n = len(data)
        op = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "repeat", "number"]))
        if n == 0:
            op = "insert"
        i = draw(st.integers(0, max(n - 1, 0)))
        if op == "truncate":
            data = data[:i]
        elif op == "flip":
            data = data[:i] + bytes([data[i] ^ draw(st.integers(1, 255))]) + data[i + 1 :]
        elif op == "insert":
            data = data[:i] + draw(st.binary(min_size=1, max_size=8)) + data[i:]
        elif op == "delete":
            data = data[:i] + data[i + draw(st.integers(1, 64)) :]
        elif op == "repeat":
            j = min(n, i + draw(st.integers(1, 200)))
            data = data[:j] + data[i:j] * draw(st.integers(1, 20)) + data[j:]
        else:
            nums = list(_NUM.finditer(data))
            if nums:
                m = nums[draw(st.integers(0, len(nums) - 1))]
                data = data[: m.start()] + draw(NUMBERS).encode() + data[m.end() :]
    return data


@st.composite
def mutate_bvh(draw, data: bytes) -> bytes:
    text = data.decode()
    kind = draw(st.sampled_from(["bytes", "bytes", "count", "channels", "nest", "frametime"]))
    if kind == "count":
        text = re.sub(r"Frames: \d+", f"Frames: {draw(NUMBERS)}", text)
    elif kind == "channels":
        hits = list(re.finditer(r"CHANNELS \d+", text))
        m = hits[draw(st.integers(0, len(hits) - 1))]
        text = text[: m.start()] + f"CHANNELS {draw(NUMBERS)}" + text[m.end() :]
    elif kind == "nest":
        depth = draw(st.sampled_from([1, 10, 300, 2000]))
        block = "JOINT n\n{\nOFFSET 0 1 0\n" * depth + "}\n" * depth
        i = text.index("JOINT")
        text = text[:i] + block + text[i:]
    elif kind == "frametime":
        text = re.sub(r"Frame Time: \S+", f"Frame Time: {draw(NUMBERS)}", text)
    data = text.encode()
    if kind == "bytes" or draw(st.booleans()):
        data = draw(mutate(data))
    return data


@st.composite
def mutate_deepmimic(draw, data: bytes) -> bytes:
    kind = draw(st.sampled_from(["bytes", "bytes", "duration", "frames", "nest", "value"]))
    if kind != "bytes":
        doc = json.loads(data)
        frames = doc["Frames"]
        k = draw(st.integers(0, len(frames) - 1))
        if kind == "duration":
            frames[k][0] = draw(st.sampled_from([1e6, 1e3, 0.0, -1.0, 1e-300, 1e300, 5.0, 11.0]))
        elif kind == "frames":
            doc["Frames"] = frames * draw(st.integers(0, 30)) + [
                frames[0][: draw(st.integers(0, 44))]
            ]
        elif kind == "value":
            frames[k][draw(st.integers(0, 43))] = draw(
                st.one_of(
                    st.floats(allow_nan=False, allow_infinity=False), st.just(0), st.just(None)
                )
            )
        data = json.dumps(doc).encode()
        if kind == "nest":
            depth = draw(st.sampled_from([5, 300, 5000, 100_000]))
            data = b'{"Frames": ' + b"[" * depth + b"1" + b"]" * depth + b"}"
    if kind == "bytes" or draw(st.booleans()):
        data = draw(mutate(data))
    return data


def npz_members(data: bytes) -> dict[str, bytes]:
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        return {i.filename: z.read(i) for i in z.infolist()}


def npz_bytes(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for name, b in members.items():  # a fixed date: the same draws give the same bytes
            z.writestr(zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0)), b)
    return buf.getvalue()


def npy_with_header(shape: tuple[int, ...], descr: str, payload: bytes) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": descr, "fortran_order": False, "shape": shape}
    )
    return buf.getvalue() + payload


@st.composite
def mutate_model(draw, data: bytes) -> bytes:
    kind = draw(st.sampled_from(["bytes", "bytes", "header", "member", "meta", "array"]))
    if kind == "bytes":
        return draw(mutate(data))
    members = npz_members(data)
    names = sorted(members)
    name = draw(st.sampled_from(names))
    if kind == "header":
        shape = draw(
            st.sampled_from([(100000, 100000), (2**40,), (), (0,), (3,), (-1,), (2**62, 2**62)])
        )
        descr = draw(st.sampled_from(["<f8", "|O", "<U10", "|b1", "<i8", "V8", "<c16"]))
        members[name] = npy_with_header(shape, descr, b"\0" * draw(st.integers(0, 64)))
    elif kind == "member":
        extra = f"{draw(st.sampled_from(['junk', 'texton.extra', 'feature_map.x', 'M']))}"
        members[f"{extra}.npy" if draw(st.booleans()) else extra] = members[name]
    elif kind == "meta":
        meta = json.loads(np.load(io.BytesIO(members["__meta_json__.npy"])).tobytes())
        key = draw(st.sampled_from(sorted(meta)))
        meta[key] = draw(
            st.one_of(
                st.none(),
                st.integers(),
                st.text(max_size=5),
                st.just([[[[]]]]),
                st.just({"a": 1}),
                st.just("[" * 5000),
            )
        )
        raw = json.dumps(meta).encode()
        if draw(st.booleans()):
            raw = b"[" * 3000 + raw + b"]" * 3000
        arr = io.BytesIO()
        np.save(arr, np.frombuffer(raw, np.uint8))
        members["__meta_json__.npy"] = arr.getvalue()
    else:
        a = np.load(io.BytesIO(members[name]))
        if a.size and a.dtype.kind in "fi":
            a = a.copy()
            flat = a.reshape(-1)
            j = draw(st.integers(0, flat.size - 1))
            vals = (
                [np.nan, np.inf, -1.0, 0.0, 1e300, -5.0, 2.0]
                if a.dtype.kind == "f"
                else [-1, 2**31, 10**6]
            )
            flat[j] = draw(st.sampled_from(vals))
            if draw(st.booleans()):
                a = a[..., :-1] if a.ndim else a
        out = io.BytesIO()
        np.save(out, a)
        members[name] = out.getvalue()
    data = npz_bytes(members)
    if draw(st.booleans()):
        data = draw(mutate(data))
    return data


# ---------------------------------------------------------------------------------------------
# the property: finite data or ValueError
# ---------------------------------------------------------------------------------------------
def finite_motion(m: mj.Motion) -> None:
    arrays = [m.root_positions, m.rotations, m.local_positions]
    assert all(np.isfinite(np.asarray(a)).all() for a in arrays if a is not None)
    assert np.isfinite(np.asarray(m.skeleton.offsets_array)).all() and m.fps > 0


def finite_leaves(obj) -> None:
    for leaf in jax.tree_util.tree_leaves(obj):
        a = np.asarray(leaf)
        if a.dtype.kind == "f":
            assert np.isfinite(a).all()


def read_bvh(data: bytes, path: Path) -> None:
    path.write_bytes(data)
    finite_motion(mj.read_bvh(path))


def read_deepmimic(data: bytes, path: Path) -> None:
    path.write_bytes(data)
    finite_motion(mj.read_deepmimic(path))


def read_texture(data: bytes, path: Path) -> None:
    path.write_bytes(data)
    finite_leaves(mj.load_texture(path))


def read_feature_map(data: bytes, path: Path) -> None:
    path.write_bytes(data)
    fm = mj.load_feature_map(path)
    assert np.isfinite(np.asarray(fm.offset)).all() and np.isfinite(np.asarray(fm.scale)).all()


def check(kind: str, reader: Callable[[bytes, Path], None], data: bytes, path: Path) -> None:
    COUNTS[kind] = COUNTS.get(kind, 0) + 1
    try:
        reader(data, path)
    except ValueError:
        pass  # the one allowed failure; anything else propagates and fails the test


CASES = {
    "bvh": (read_bvh, mutate_bvh, "x.bvh"),
    "deepmimic": (read_deepmimic, mutate_deepmimic, "x.txt"),
    "texture": (read_texture, mutate_model, "x.npz"),
    "feature_map": (read_feature_map, mutate_model, "x.npz"),
}
# mutated inputs per kind: default run (>= 2,000 in all) and slow run (>= 50,000)
DEFAULT = {"bvh": 800, "deepmimic": 600, "texture": 400, "feature_map": 400}
SLOW = {k: 12_500 for k in DEFAULT}


def fuzz(kind: str, n: int, seeds: dict[str, bytes], folder: Path) -> None:
    reader, strategy, name = CASES[kind]
    path = folder / name

    @settings(
        max_examples=n,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
        derandomize=True,
    )
    @given(strategy(seeds[kind]))
    def run(data: bytes) -> None:
        check(kind, reader, data, path)

    before, t0 = COUNTS.get(kind, 0), time.perf_counter()
    STARTED[:] = STARTED or [t0]
    run()
    done = COUNTS[kind] - before
    print(f"\nfuzz {kind}: {done:,} mutated inputs in {time.perf_counter() - t0:.1f} s")
    assert done >= n


@pytest.mark.parametrize("kind", list(DEFAULT))
def test_fuzz(kind, seeds, tmp_path):
    fuzz(kind, DEFAULT[kind], seeds, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("kind", list(SLOW))
def test_fuzz_slow(kind, seeds, tmp_path):
    fuzz(kind, SLOW[kind], seeds, tmp_path)


# ---------------------------------------------------------------------------------------------
# the memory budget: hostile inputs in a subprocess under RLIMIT_AS
# ---------------------------------------------------------------------------------------------
BUDGET = 1536 << 20  # bytes of address space above the baseline after imports and warm-up

CHILD = textwrap.dedent(
    """
    import io, json, resource, sys, zipfile
    from pathlib import Path
    import numpy as np
    import jax
    jax.config.update("jax_enable_x64", True)
    import mtex_jax as mj

    folder = Path(sys.argv[1])
    budget = int(sys.argv[2])
    dm = json.loads(Path(sys.argv[3]).read_text())
    mj.read_deepmimic(sys.argv[3])  # warm-up: every import and code path in place
    mj.load_texture(folder / "tex.npz")

    def vm(field):
        for line in open("/proc/self/status"):
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024

    base = vm("VmSize")
    resource.setrlimit(resource.RLIMIT_AS, (base + budget, base + budget))
    hostile = []
    for seconds in (1e6, 1e9, 3e5):
        d = json.loads(json.dumps(dm))
        d["Frames"][1][0] = seconds
        p = folder / f"long{seconds:g}.txt"
        p.write_text(json.dumps(d))
        hostile.append((mj.read_deepmimic, p))
    p = folder / "deep.txt"
    p.write_text('{"Frames": ' + "[" * 1_000_000 + "]" * 1_000_000 + "}")
    hostile.append((mj.read_deepmimic, p))
    lines = ["HIERARCHY", "ROOT r", "{", "OFFSET 0 0 0"]
    lines += ["JOINT j", "{", "OFFSET 0 1 0"] * 100_000 + ["}"] * 100_001
    lines += ["MOTION", "Frames: 1", "Frame Time: 0.01", "0"]
    p = folder / "deep.bvh"
    p.write_text("\\n".join(lines))
    hostile.append((mj.read_bvh, p))
    p = folder / "frames.bvh"
    p.write_text("\\n".join(["HIERARCHY", "ROOT r", "{", "OFFSET 0 0 0",
                            "CHANNELS 3 Xposition Yposition Zposition", "}", "MOTION",
                            "Frames: 1e15", "Frame Time: 0.01", "0 0 0"]))
    hostile.append((mj.read_bvh, p))
    src = (folder / "tex.npz").read_bytes()
    with zipfile.ZipFile(io.BytesIO(src)) as z:
        members = {i.filename: z.read(i) for i in z.infolist()}
    for shape, descr in (((100000, 100000), "<f8"), ((2**27,), "<f8"), ((2**24,), "<f8")):
        h = io.BytesIO()
        np.lib.format.write_array_header_1_0(
            h, {"descr": descr, "fortran_order": False, "shape": shape})
        m = dict(members)
        n_bytes = int(np.prod(shape)) * 8
        # 128 MiB of zeros really in the archive (a zip bomb: zeros compress 1000:1): within
        # the member limit, read, then refused (M has the wrong shape); the others declare
        # more than the limit or than their member holds and are refused before allocation
        m["M.npy"] = h.getvalue() + (b"\\0" * n_bytes if n_bytes <= 2**27 else b"\\0" * 64)
        p = folder / f"bomb{len(hostile)}.npz"
        with zipfile.ZipFile(p, "w", zipfile.ZIP_DEFLATED) as z:
            for name, b in m.items():
                z.writestr(name, b)
        del m
        hostile.append((mj.load_texture, p))
    for reader, path in hostile:
        try:
            reader(path)
            print("ACCEPTED", path)
        except ValueError as e:
            print("OK", str(e)[:100])
    print("PEAK", vm("VmPeak") - base)
    """
)


def test_memory_budget_on_hostile_inputs(seeds, tmp_path):
    """Hostile inputs stay within ``BUDGET`` bytes of address space above the baseline.

    ``RLIMIT_AS`` is set in the child after ``import jax`` and a warm-up read (JAX and XLA
    reserve several GiB of virtual address space when they start, which a limit set before
    the imports would have to include): a read that tried to allocate more than the budget
    would fail with ``MemoryError`` there (and the test with it).
    """
    (tmp_path / "tex.npz").write_bytes(seeds["texture"])
    dm = tmp_path / "dm.txt"
    dm.write_bytes(seeds["deepmimic"])
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=1")
    r = subprocess.run(
        [sys.executable, "-c", CHILD, str(tmp_path), str(BUDGET), str(dm)],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    oks = [ln for ln in lines if ln.startswith("OK")]
    assert len(oks) == 9 and not any(ln.startswith("ACCEPTED") for ln in lines), r.stdout
    peak = int(lines[-1].split()[1])
    # VmPeak above the baseline (measured: 277 MB, mostly the 128 MiB member)
    assert peak < BUDGET, peak
    COUNTS["memory"] = len(oks)


def test_zz_fuzz_count(capsys):
    """The count of mutated inputs read by this run (printed; at least 2,000 in the default
    run when every fuzz test above ran)."""
    total = sum(v for k, v in COUNTS.items() if k != "memory")
    elapsed = time.perf_counter() - STARTED[0] if STARTED else 0.0
    with capsys.disabled():
        print(f"\nfuzz: {total:,} mutated inputs {COUNTS} in {elapsed:.1f} s")
    if all(COUNTS.get(k, 0) >= n for k, n in DEFAULT.items()):
        assert total >= 2000
