"""Data-parallel learning over the processes of a ``jax.distributed`` job
(:func:`learn_distributed`; design §4.8, §10.6): :func:`learn` on the union of the processes'
clips, to rounding. It runs the same EM loop (:func:`~.loop.run_em`) and model selection as
:func:`learn`; only its runner's E- and M-steps differ (:class:`_DistRunner`).

- Preparation (once): the clips are sent to every process for the checks, the feature map and
  the state dimension, done on the union as :func:`learn` does; process 0 runs the greedy
  initialisation (sequential over the clips) and sends the segments. Then each process keeps
  only its own clips.
- E-step: each process segments its own clips; the segment rows and per-clip scores are
  gathered, so every process holds the global segmentation (clips numbered in process order).
- M-step: pass-1 statistics per texton on the local segments, summed across processes; the
  subspaces; pass-2 statistics, summed; the textons. Transitions, durations, pruning, the
  objective's transition terms and the convergence test use the global segmentation, so
  every process takes the same decisions.

The M-step's statistics are summed by an all-reduce over one device per process; everything
else travels as all-gathers of host bytes (bit-exact at any precision setting).
"""

from __future__ import annotations

import dataclasses
import functools
import io
import json
import os
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils

from ...motion import FeatureMap, Motion, Skeleton
from .._config import LearnConfig
from .._model import MotionTexture
from .._segmentation.segment import check_lengths
from .._texton.texton import Texton
from .checkpoint import Checkpoint, Peers, learn_digest
from .contacts import with_contacts
from .em import NO_PADDING, Capacity, Runner, warm_start
from .init import Segs, greedy_init
from .labels import capacity_for, transition_counts
from .learn import (
    check_data,
    em_and_selection,
    greedy_segments,
    resolve_state_dim,
    threshold_bic,
    with_innovations,
)
from .loop import EMSettings
from .mstep import dynamics_pass, frame_pass, solve_texton, subspaces_from

__all__ = ["learn_distributed"]


# ---------------------------------------------------------------------------------------------
# Collectives on host data
# ---------------------------------------------------------------------------------------------
def _allgather_bytes(payload: bytes) -> list[bytes]:
    """Every process's ``payload``, in process order (a collective: all processes call it)."""
    n = len(payload)
    sizes = np.asarray(multihost_utils.process_allgather(np.asarray([n], np.int32))).reshape(-1)
    # buffers of a power-of-two length: few shapes, so few compilations of the gather
    width = 1 << max(4, int(sizes.max() - 1).bit_length())
    buf = np.zeros(width, np.uint8)
    buf[:n] = np.frombuffer(payload, np.uint8)
    out = np.asarray(multihost_utils.process_allgather(buf)).reshape(len(sizes), width)
    return [out[p, : int(sizes[p])].tobytes() for p in range(len(sizes))]


def _pack(arrays: dict[str, np.ndarray]) -> bytes:
    f = io.BytesIO()
    np.savez(f, allow_pickle=False, **arrays)
    return f.getvalue()


def _unpack(payload: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(payload), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _allgather_arrays(arrays: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
    return [_unpack(b) for b in _allgather_bytes(_pack(arrays))]


@functools.cache
def _process_sum(n_proc: int) -> tuple[jax.sharding.NamedSharding, Callable[..., Any]]:
    """A global ``(processes, …)`` layout (one device per process) and a jitted sum over its
    first axis whose result every device holds: XLA's all-reduce (gloo's on CPU)."""
    devices = [jax.local_devices(process_index=p)[0] for p in range(n_proc)]
    mesh = jax.sharding.Mesh(np.asarray(devices), ("p",))
    spec = jax.sharding.PartitionSpec
    rows = jax.sharding.NamedSharding(mesh, spec("p"))
    replicated = jax.sharding.NamedSharding(mesh, spec())
    return rows, jax.jit(lambda xs: [jnp.sum(x, axis=0) for x in xs], out_shardings=replicated)


def _allreduce(tree: Any) -> Any:
    """The sum over processes of a pytree of arrays: an all-reduce, so each process sends and
    receives about the size of the tree (not processes × size), and every process gets the
    same result."""
    n_proc = jax.process_count()
    if n_proc == 1:
        return tree
    leaves, treedef = jax.tree.flatten(tree)
    rows, total = _process_sum(n_proc)
    glob = [jax.make_array_from_process_local_data(rows, np.asarray(a)[None]) for a in leaves]
    summed = [jnp.asarray(np.asarray(o.addressable_data(0))) for o in total(glob)]
    return jax.tree.unflatten(treedef, summed)


def _json_array(obj: Any) -> np.ndarray:
    return np.frombuffer(json.dumps(obj).encode(), np.uint8)


def _json_of(a: np.ndarray) -> Any:
    return json.loads(a.tobytes().decode())


def _error(e: Exception) -> dict[str, np.ndarray]:
    return {"error": _json_array([type(e).__name__, str(e)])}


def _raise_first_error(parts: list[dict[str, np.ndarray]]) -> None:
    """Raise the first process's error on every process (all of them hold the same parts)."""
    for p, part in enumerate(parts):
        if "error" in part:
            kind, msg = _json_of(part["error"])
            exc = TypeError if kind == "TypeError" else ValueError
            raise exc(f"learn_distributed: process {p}: {msg}")


def _from_root(fn: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """``fn()`` run on process 0 only, its result sent to every process (an error there is
    raised on every process)."""
    payload = b""
    if jax.process_index() == 0:
        try:
            payload = _pack(fn())
        except (ValueError, TypeError) as e:
            payload = _pack(_error(e))
    got = _unpack(_allgather_bytes(payload)[0])
    _raise_first_error([got])
    return got


# ---------------------------------------------------------------------------------------------
# Exchanging the clips (for the checks, the feature map and the greedy initialisation)
# ---------------------------------------------------------------------------------------------
def _local_payload(data: Any, config: LearnConfig) -> dict[str, np.ndarray]:
    """This process's clips (motions resampled to ``config.fps``) as arrays and a JSON header;
    a bad input becomes an ``error`` entry, raised on every process after the exchange."""
    try:
        if not isinstance(config, LearnConfig):
            raise TypeError(f"config must be a LearnConfig, got {type(config).__name__}")
        if isinstance(data, Motion) or getattr(data, "ndim", 0) == 2:
            data = [data]
        clips = list(data)
        if not clips:
            raise ValueError(
                "has no clips; every process of a distributed learn needs at least one"
            )
        arrays: dict[str, np.ndarray] = {}
        meta: list[dict[str, Any]] = []
        for i, c in enumerate(clips):
            if isinstance(c, Motion):
                m = (c if config.fps is None else c.resample(config.fps)).numpy()
                arrays[f"{i}.root"] = np.asarray(m.root_positions)
                arrays[f"{i}.rot"] = np.asarray(m.rotations)
                if m.local_positions is not None:
                    arrays[f"{i}.lp"] = np.asarray(m.local_positions)
                meta.append({"fps": m.fps, "skeleton": m.skeleton.to_json_dict()})
            else:
                a = np.asarray(c)
                if a.dtype.kind not in "biuf":
                    raise TypeError(f"clip {i} has dtype {a.dtype}, expected numbers")
                arrays[f"{i}.y"] = a
                meta.append({})
        header = {"config": config.to_json_dict(), "clips": meta}
    except (ValueError, TypeError) as e:
        return _error(e)
    return {**arrays, "header": _json_array(header)}


def _clips_of(part: dict[str, np.ndarray]) -> list[Any]:
    out: list[Any] = []
    skeletons: dict[str, Skeleton] = {}
    for i, meta in enumerate(_json_of(part["header"])["clips"]):
        if not meta:
            out.append(part[f"{i}.y"])
            continue
        key = json.dumps(meta["skeleton"], sort_keys=True)
        if key not in skeletons:
            skeletons[key] = Skeleton.from_json_dict(meta["skeleton"])
        lp = part.get(f"{i}.lp")
        out.append(
            Motion(skeletons[key], float(meta["fps"]), part[f"{i}.root"], part[f"{i}.rot"], lp)
        )
    return out


def _exchange_clips(data: Any, config: LearnConfig) -> tuple[list[Any], list[int]]:
    """All processes' clips in process order, and the number each process holds."""
    parts = _allgather_arrays(_local_payload(data, config))
    _raise_first_error(parts)
    for p, part in enumerate(parts):
        if _json_of(part["header"])["config"] != _json_of(parts[0]["header"])["config"]:
            _raise_first_error(
                [{}] * p + [_error(ValueError("its LearnConfig differs from process 0's"))]
            )
    clips = [_clips_of(part) for part in parts]
    return [c for cs in clips for c in cs], [len(cs) for cs in clips]


# ---------------------------------------------------------------------------------------------
# The runner: local data, collective steps
# ---------------------------------------------------------------------------------------------
class _DistRunner(Runner):
    """The EM steps of :class:`Runner` over this process's clips, with the cross-clip
    reductions done across processes. Segments (``segs``) are global: the clip index ``s``
    counts the clips of every process in process order."""

    def __init__(
        self,
        ys_local: list[np.ndarray],
        config: LearnConfig,
        counts: Sequence[int],
        T: int,
        n_frames: int,
    ) -> None:
        # the global T: the single-process shapes; this process's devices only
        super().__init__(ys_local, config, jax.local_devices(), T)
        self.offset = int(sum(counts[: jax.process_index()]))
        self.n_real = int(sum(counts))  # every process's clips
        self.n_frames = n_frames  # every process's frames

    def _mine(self, segs: Segs) -> np.ndarray:
        """Which rows of the global ``segs`` are this process's."""
        return (segs[:, 0] >= self.offset) & (segs[:, 0] < self.offset + len(self.ys))

    def _local_rows(self, segs: Segs) -> Segs:
        rows = segs[self._mine(segs)].copy()
        rows[:, 0] -= self.offset
        return rows

    def m_step(
        self,
        segs: Segs,
        n_textons: int,
        capacity: Capacity = NO_PADDING,
        rows_valid: np.ndarray | None = None,
        prev: Texton | None = None,
    ) -> tuple[Texton, np.ndarray, np.ndarray]:
        """:meth:`Runner.m_step` on this process's rows of the global ``segs``, with the
        statistics summed across processes (design §10.6)."""
        local = self._local_rows(segs)
        n = len(local)
        cap = self._cap("rows", capacity_for(max(n, 1)))
        rows = np.zeros((cap, 4), dtype=np.int64)
        rows[:n] = local
        valid = np.arange(cap) < n
        if rows_valid is not None:
            valid[:n] &= rows_valid[self._mine(segs)]
        rows_j, valid = jnp.asarray(rows), jnp.asarray(valid)
        n_tex = self.m_stack(n_textons, capacity)
        assert self.config.state_dim is not None  # resolved before EM
        fs = _allreduce(frame_pass(self.Y, rows_j, valid, n_tex, self.tmax))
        sub = subspaces_from(fs, self.config.state_dim, float(self.config.sigma2_floor))
        # Student-t textons: the reweightings of the single-process M-step (from the Gaussian
        # fit, or one from the E-step's textons), each one all-reduce of the weighted sums
        warm = warm_start(prev, n_tex, self.opts)
        if warm is None:
            ds = dynamics_pass(self.Y, rows_j, valid, sub, self.tmax)
            tex = solve_texton(sub, _allreduce(ds), self.opts)
            steps = self.opts.irls_steps if self.opts.dof is not None else 0
        else:
            tex, steps = warm, 1
        for _ in range(steps):
            ds = dynamics_pass(self.Y, rows_j, valid, sub, self.tmax, tex)
            tex = solve_texton(sub, _allreduce(ds), self.opts)
        M, pi = transition_counts(segs, n_textons, self.config.pseudo_count)
        return tex, M, pi

    def e_step(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        log_d: np.ndarray | None = None,
        capacity: Capacity = NO_PADDING,
    ) -> tuple[Segs, float]:
        """:meth:`Runner.e_step` of every process's clips, gathered."""
        rows, score, _ = self._gathered_e_step(tex, M, pi, log_d, capacity, None)
        return rows, score

    def e_step_scored(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        log_d: np.ndarray | None,
        segs: Segs,
        capacity: Capacity = NO_PADDING,
    ) -> tuple[Segs, float, float]:
        """:meth:`Runner.e_step_scored` of every process's clips, gathered."""
        return self._gathered_e_step(tex, M, pi, log_d, capacity, segs)

    def _gathered_e_step(
        self,
        tex: Texton,
        M: np.ndarray,
        pi: np.ndarray,
        log_d: np.ndarray | None,
        capacity: Capacity,
        segs: Segs | None,
    ) -> tuple[Segs, float, float]:
        """Every process's segmentations and scores (and its clips' sums of the scores of
        ``segs``), gathered."""
        local = None if segs is None else self._local_rows(segs)
        rows, scores, old = self._segment_clips(tex, M, pi, log_d, capacity, local)
        rows[:, 0] += self.offset
        old = np.zeros(1) if old is None else old
        parts = _allgather_arrays({"rows": rows, "scores": scores, "old": old})
        all_rows = np.concatenate([p["rows"] for p in parts]).astype(np.int64)
        all_scores = np.concatenate([p["scores"] for p in parts])
        old_sum = float(sum(float(p["old"].sum()) for p in parts))
        return all_rows.reshape(-1, 4), float(all_scores.sum()), old_sum

    def key_poses(self, segs: Segs) -> np.ndarray:
        """:meth:`Runner.key_poses` of every process's segments, gathered."""
        mine = self._mine(segs)
        local = super().key_poses(self._local_rows(segs))
        parts = _allgather_arrays({"key": local, "mine": mine})
        out = np.empty((len(segs), *local.shape[1:]), local.dtype)
        for p in parts:
            out[p["mine"]] = p["key"]
        return out


# ---------------------------------------------------------------------------------------------
# learn_distributed
# ---------------------------------------------------------------------------------------------
def _initial_segments(
    ys: list[np.ndarray], config: LearnConfig, verbose: bool, t0: float
) -> dict[str, np.ndarray]:
    """Greedy initialisation as :func:`learn` does it (run on process 0 only)."""
    if config.threshold is None and config.n_textons is None and config.bic_thresholds:
        return {
            f"segs{i}": greedy_init(ys, config, float(th))[0]
            for i, th in enumerate(config.bic_thresholds)
        }
    threshold, segs = greedy_segments(ys, config, verbose, t0)
    return {"segs0": segs, "threshold": np.asarray([threshold], np.float64)}


def _prepare(
    data: Any, config: LearnConfig, verbose: bool, digest: bool = False
) -> tuple[_DistRunner, FeatureMap | None, LearnConfig, dict[str, np.ndarray], str]:
    """The exchange of the clips, the checks, the feature map, the state dimension and the
    initial segments (from process 0) as :func:`learn` does them on the union; the runner
    keeps this process's clips only. With ``digest``, the checkpoint digest of the union
    (:func:`~.checkpoint.learn_digest`, the same on every process), else ``""``."""
    clips, counts = _exchange_clips(data, config)
    # the motions arrive resampled: the checks must not resample them again
    ys, fm, _ = check_data(clips, dataclasses.replace(config, fps=None))
    T = max(y.shape[0] for y in ys)
    check_lengths(config.tmin, config.tmax, T)
    dig = learn_digest(ys, config) if digest else ""
    config = resolve_state_dim(ys, config, verbose)
    t0 = time.perf_counter()
    init = _from_root(lambda: _initial_segments(ys, config, verbose, t0))
    me = jax.process_index()
    offset = sum(counts[:me])
    n_frames = sum(y.shape[0] for y in ys)
    run = _DistRunner(ys[offset : offset + counts[me]], config, counts, T, n_frames)
    return run, fm, config, init, dig


def _peers() -> Peers:
    """The processes of the job, for a checkpoint: process 0 reads and writes it."""

    def gather(obj: Any) -> list[Any]:
        parts = _allgather_bytes(json.dumps(obj).encode("utf-8"))
        return [json.loads(p.decode("utf-8")) for p in parts]

    return Peers(jax.process_index(), jax.process_count(), _from_root, gather)


def learn_distributed(
    data: Sequence[Motion] | Sequence[Any] | Motion,
    config: LearnConfig | None = None,
    *,
    verbose: bool = False,
    callback: Callable[[dict[str, Any]], None] | None = None,
    checkpoint: str | os.PathLike[str] | None = None,
    resume: bool = False,
) -> MotionTexture:
    """Learn a motion texture with the clips spread over the processes of a JAX job.

    Data-parallel :func:`learn`: every process of a job started with
    ``jax.distributed.initialize`` calls this function with its own clips and the same
    ``config``. Each process segments its own clips (the E-step) and computes the M-step's
    sufficient statistics on them; the statistics are summed across processes, and every
    process returns the same model: :func:`learn` on all the clips, taken in process order
    (process 0's clips first), to rounding. Its ``segments`` number the clips in that order.

    What is not data-parallel: the clips are sent to every process once, for the checks, the
    feature map, the choice of the state dimension and the greedy initialisation, which runs
    on process 0 (it is sequential over the clips) and is broadcast; afterwards each process
    keeps only its own clips. All model selection works distributed: ``config.selection="bic"``
    (backward elimination: its E-steps and EM runs are distributed like the others) and
    ``config.bic_thresholds`` (every threshold's initialisation on process 0, then EM).

    The library never initialises the runtime nor changes JAX's configuration; the program
    does, before any other use of JAX. Two CPU processes on one machine:

    .. code-block:: python

        import jax
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize("127.0.0.1:12355", num_processes=2, process_id=pid,
                                   local_device_ids=[0])
        model = learn_distributed(my_clips, LearnConfig(fps=60.0))

    On several hosts, run one process per host (its clips split over the host's local devices
    as ``config.shard`` says) or one per accelerator (``local_device_ids=[i]``), every process with
    the coordinator's ``host:port`` (a port process 0's host can open), ``num_processes`` and
    its own ``process_id``; on a cluster whose launcher JAX recognises (SLURM, Open MPI,
    Cloud TPU) a bare ``jax.distributed.initialize()`` finds them. ``mtex learn
    --distributed`` does this from flags or environment variables.

    With a single process (no ``jax.distributed``) it equals :func:`learn`, the clips'
    contact model included; with several, the model carries none (no process sees every clip's
    feet): pass one to ``clean`` (``mtex synth --clean --contacts``). The clips' content
    travels through JAX's collectives (on CPU: gloo over TCP); the processes must be
    trusted peers of one job.

    Args:
        data: this process's clips: a list of :class:`Motion` (one skeleton on all processes)
            or of ``(T_s, D)`` arrays (one ``D`` on all processes); at least one.
        config: :class:`LearnConfig`, the same on every process.
        verbose: print progress (on process 0 only).
        callback: called on every process after every EM iteration, as in :func:`learn`.
        checkpoint: as in :func:`learn`, the same path on every process: process 0 writes
            it after every EM iteration (with every process's padded sizes) and, with
            ``resume``, reads it and sends it to the others (design §4.9), so the file need
            be on process 0's disk only. A resumed distributed learn equals an uninterrupted
            one bit for bit; the checkpoint is refused if the job has another number of
            processes.
        resume: continue from ``checkpoint`` if it exists on process 0.

    Returns:
        The :class:`MotionTexture`, the same on every process.

    Raises:
        ValueError: a process has no clips, the processes' configurations differ, or any
            error of :func:`learn` on the union (clip indices count in process order); it is
            raised on every process.
        TypeError: ``config`` is not a :class:`LearnConfig`, or clips are neither motions
            nor numeric arrays (on every process).
    """
    config = LearnConfig() if config is None else config
    root = jax.process_index() == 0
    if checkpoint is not None and (
        config.threshold is None and config.n_textons is None and config.bic_thresholds
    ):
        raise ValueError(
            "checkpoint: a learn that tries every threshold of bic_thresholds is not "
            "checkpointed; give threshold or n_textons"
        )
    run, fm, config, init, digest = _prepare(data, config, verbose and root, checkpoint is not None)
    ck = None
    if checkpoint is not None:
        ck = Checkpoint(checkpoint, digest, resume, run, _peers())
        if ck.resumed and verbose and root:
            print(f"[mtex learn] resuming from {checkpoint} ({ck.saved_stage()})", flush=True)
    settings = EMSettings(fm, verbose and root, callback)
    if "threshold" not in init:  # bic_thresholds: initialisation + EM for each, lowest BIC
        thresholds = config.bic_thresholds or ()
        segs = {float(th): init[f"segs{i}"] for i, th in enumerate(thresholds)}
        _, table, models = threshold_bic(run, config, thresholds, segs.__getitem__, settings)
        model = models[int(np.argmin([r["bic"] for r in table]))]
    else:
        threshold = float(init["threshold"][0])
        model = em_and_selection(run, config, threshold, init["segs0"], settings, ck)
    model = _with_innovations(model, run)
    if jax.process_count() == 1:  # equals learn: the clips' contact model (design §6.6)
        clips = [data] if isinstance(data, Motion) else list(data)
        if clips and all(isinstance(c, Motion) for c in clips):
            model = with_contacts(model, clips, verbose)
    return model


def _with_innovations(model: MotionTexture, run: _DistRunner) -> MotionTexture:
    """The innovation process of the model from every process's residuals (summed
    statistics; for a residual bank the residuals themselves, gathered), the same on every
    process."""
    if jax.process_count() == 1:  # equals learn (residual banks included)
        return with_innovations(model, run.ys)
    return with_innovations(
        model,
        run.ys,
        run.offset,
        reduce=lambda st: np.asarray(_allreduce(jnp.asarray(st))),
        gather=_allgather_arrays,
    )
