"""Checkpoints of a learn (design §4.9): the progress of the EM runs on disk, so that a learn
that is stopped resumes to the model an uninterrupted learn gives, bit for bit.

A learn is a fixed sequence of stages, each deterministic given the clips and the
configuration: EM on the initial segments (``"em"``), the selection of the textons
(``"selection"``: rounds, each an E-step without some textons and possibly a short EM refit)
and EM on the selected textons (``"final"``). After every EM iteration the checkpoint holds:

- the stage, and in the selection the round's state (the best model so far, its criterion and
  the number of textons to drop next);
- the running EM's :class:`~.loop.EMState`;
- the runner's padded sizes (a compile cache; kept so that a resumed run pads as the
  uninterrupted one did), one set per process of a distributed learn.

Work between two iterations (the greedy initialisation, a selection round's E-step) is done
again on resume: it is deterministic. The file is the model file's format (``.npz`` arrays and
JSON metadata, written atomically, never a pickle) and carries a digest of the clips and the
configuration: a checkpoint of other data or another configuration is refused.

A distributed learn (:func:`~.distributed.learn_distributed`) holds the same EM state on every
process: process 0 reads and writes the file, sends what it read to the others, and gathers
their padded sizes at every save (the :class:`Peers` of the job).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ...core import load_arrays_json, save_arrays_json
from .._config import LearnConfig
from .._model import MotionTexture, texton_arrays, texton_of_arrays, texture_of_arrays_json
from .._texton.texton import Texton
from .loop import EMState, Fit

__all__ = ["CHECKPOINT_KIND", "Checkpoint", "Peers", "SelectionState", "learn_digest"]

CHECKPOINT_KIND = "mtex_jax.LearnCheckpoint"
_VERSION = 2  # 2: the padded sizes of every process
STAGES = ("em", "selection", "final")


def learn_digest(ys: list[np.ndarray], config: LearnConfig) -> str:
    """A digest of the clips (shapes, dtypes, bytes) and the configuration: what a checkpoint
    must have been made from to be resumed."""
    h = hashlib.sha256()
    h.update(json.dumps(config.to_json_dict(), sort_keys=True).encode())
    for y in ys:
        a = np.ascontiguousarray(y)
        h.update(f"{a.shape}{a.dtype.str}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


@dataclasses.dataclass(frozen=True)
class SelectionState:
    """The selection between two rounds (:func:`~.learn._backward_bic`).

    Attributes:
        best: the best model so far.
        best_value: its criterion.
        m: the number of textons the next round drops (before its bound by half the
            textons).
        round: rounds done.
        m_cap: the M-step's stack size of every round (the first model's).
        capacity: the stack sizes of the last round (when the selection is done: those of
            the final EM).
    """

    best: MotionTexture
    best_value: float
    m: int
    round: int
    m_cap: int
    capacity: tuple[int, int] = (1, 1)


def _put_optional(arrays: dict[str, np.ndarray], key: str, a: Any) -> None:
    if a is not None:
        arrays[key] = np.asarray(a)


def _state_arrays(state: EMState) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays: dict[str, np.ndarray] = {"em.segs": np.asarray(state.segs)}
    meta: dict[str, Any] = {
        "iteration": state.iteration,
        "prune_initial": state.prune_initial,
        "converged": state.converged,
        "textons": None,
        "best": None,
    }
    arrays["em.history"] = np.asarray(state.history, dtype=np.float64).reshape(-1, 2)
    if state.textons is not None:
        a, meta["textons"] = texton_arrays(state.textons, "em.textons.")
        arrays.update(a)
    for name in ("M", "pi", "log_d"):
        _put_optional(arrays, f"em.{name}", getattr(state, name))
    if state.best is not None:
        b = state.best
        a, tmeta = texton_arrays(b.textons, "em.best.textons.")
        arrays.update(a)
        arrays["em.best.objective"] = np.asarray(b.objective, dtype=np.float64)
        arrays["em.best.M"] = np.asarray(b.M)
        arrays["em.best.pi"] = np.asarray(b.pi)
        arrays["em.best.segs"] = np.asarray(b.segs)
        _put_optional(arrays, "em.best.log_d", b.log_d)
        meta["best"] = tmeta
    return arrays, meta


def _state_of(arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> EMState:
    textons: Texton | None = None
    if meta["textons"] is not None:
        textons = texton_of_arrays(arrays, meta["textons"], "em.textons.")
    best = None
    if meta["best"] is not None:
        best = Fit(
            float(arrays["em.best.objective"]),
            texton_of_arrays(arrays, meta["best"], "em.best.textons."),
            arrays["em.best.M"],
            arrays["em.best.pi"],
            arrays.get("em.best.log_d"),
            arrays["em.best.segs"],
        )
    history = tuple((float(a), float(b)) for a, b in arrays["em.history"])
    return EMState(
        arrays["em.segs"],
        textons,
        arrays.get("em.M"),
        arrays.get("em.pi"),
        arrays.get("em.log_d"),
        int(meta["iteration"]),
        history,
        best,
        bool(meta["prune_initial"]),
        bool(meta["converged"]),
    )


_META = "__checkpoint_meta__"


class Peers:
    """The processes a checkpoint is shared by: this process alone (the default), or the
    processes of a distributed learn (:func:`~.distributed.learn_distributed` passes its
    collectives).

    Attributes:
        index: this process's index (``0`` alone).
        count: the processes.
        writes: this process writes the file (process 0).
    """

    def __init__(
        self,
        index: int = 0,
        count: int = 1,
        share: Callable[[Callable[[], dict[str, np.ndarray]]], dict[str, np.ndarray]] | None = None,
        gather: Callable[[Any], list[Any]] | None = None,
    ) -> None:
        self.index, self.count, self.writes = index, count, index == 0
        self._share, self._gather = share, gather

    def share(self, fn: Callable[[], dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """``fn()`` run by process 0, its result (or its error) on every process."""
        return fn() if self._share is None else self._share(fn)

    def gather(self, obj: Any) -> list[Any]:
        """Every process's JSON-serialisable ``obj``, in process order."""
        return [obj] if self._gather is None else self._gather(obj)


class Checkpoint:
    """The checkpoint file of one learn: read on resume, written after every EM iteration.

    The learn calls :meth:`enter` when a stage (or a selection round's refit) starts and gets
    back the saved EM state of that stage if the checkpoint was made inside it; :meth:`save`
    after every iteration; :meth:`selection` for the saved selection state.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        digest: str,
        resume: bool,
        runner: Any,
        peers: Peers | None = None,
    ) -> None:
        """Open the checkpoint ``path`` of a learn of ``digest`` (:func:`learn_digest`) whose
        steps ``runner`` runs (its padded sizes are saved and restored with the EM state);
        ``peers``: the processes of a distributed learn (``None``: this process alone).

        Raises:
            ValueError: ``resume`` is false and ``path`` exists (a checkpoint would be
                overwritten: pass ``resume=True`` or remove it); ``resume`` is true and the
                file is not a learn checkpoint, or one of other clips or another configuration.
                In a distributed learn, on every process (process 0 looked).
        """
        self.path = Path(path)
        self.digest = digest
        self.runner = runner
        self.peers = Peers() if peers is None else peers
        self._round_caps: dict[str, int] = {}
        self._saved: tuple[dict[str, np.ndarray], dict[str, Any]] | None = None
        self.stage = "em"  # where the learn is now
        self.round = -1  # the selection round whose refit runs (stage "selection")
        self._selection: SelectionState | None = None
        self.resumed = False
        got = self.peers.share(lambda: self._read(resume))
        if got:
            meta = json.loads(got.pop(_META).tobytes().decode("utf-8"))
            self._saved = (got, meta)
            self.resumed = True

    def _read(self, resume: bool) -> dict[str, np.ndarray]:
        """The saved arrays and the metadata (as JSON bytes under ``_META``), or ``{}``."""
        if self.path.exists() and not resume:
            raise ValueError(
                f"checkpoint {self.path} exists: resume from it (resume=True, mtex learn "
                "--resume) or remove it"
            )
        if not (resume and self.path.exists()):
            return {}
        arrays, meta = load_arrays_json(self.path, kind=CHECKPOINT_KIND)
        if meta.get("format_version") != _VERSION:
            raise ValueError(
                f"{self.path}: checkpoint format {meta.get('format_version')!r} is not "
                f"supported (this mtex_jax reads version {_VERSION})"
            )
        if meta.get("digest") != self.digest:
            raise ValueError(
                f"{self.path}: this checkpoint is of other clips or another configuration "
                "than this learn; it cannot be resumed (remove it to start again)"
            )
        if meta.get("stage") not in STAGES:
            raise ValueError(f"{self.path}: unknown stage {meta.get('stage')!r}")
        n = len(meta.get("caps") or [])
        if n != self.peers.count:
            raise ValueError(
                f"{self.path}: this checkpoint is of a learn of {n} process(es), this one has "
                f"{self.peers.count}"
            )
        return {**arrays, _META: np.frombuffer(json.dumps(meta).encode("utf-8"), np.uint8)}

    # ------------------------------------------------------------------ reading
    def saved_stage(self) -> str | None:
        """The stage the checkpoint was made in (``None``: a fresh learn)."""
        return None if self._saved is None else self._saved[1]["stage"]

    def saved_selection(self) -> SelectionState | None:
        """The selection state the checkpoint holds (stages ``"selection"``, ``"final"``)."""
        if self._saved is None or self._saved[1].get("selection") is None:
            return None
        arrays, meta = self._saved
        sel = meta["selection"]
        sub = {k[len("sel.") :]: v for k, v in arrays.items() if k.startswith("sel.")}
        best = texture_of_arrays_json(sub, sel["model"])
        return SelectionState(
            best,
            float(arrays["sel_value"]),
            int(sel["m"]),
            int(sel["round"]),
            int(sel["m_cap"]),
            (int(sel["capacity"][0]), int(sel["capacity"][1])),
        )

    def _at(self, stage: str, round: int) -> bool:
        return (
            self._saved is not None
            and self._saved[1]["stage"] == stage
            and int(self._saved[1]["round"]) == round
        )

    def begin(self, stage: str, round: int = -1) -> None:
        """The learn starts ``stage`` (in the selection: round ``round``, before its E-step).
        Resuming there, the runner's padded sizes become those it had at this point."""
        self.stage, self.round = stage, round
        if self._at(stage, round):
            assert self._saved is not None
            self.runner.set_caps(self._saved[1]["round_caps"][self.peers.index])
        self._round_caps = self.runner.caps()

    def enter(self) -> EMState | None:
        """The learn starts the EM of the current stage (:meth:`begin`); the EM state to
        continue from, with the runner's padded sizes of then, if the checkpoint was made
        there, else ``None``."""
        if not self._at(self.stage, self.round):
            return None
        assert self._saved is not None
        arrays, meta = self._saved
        state = _state_of(arrays, meta["em"])
        self.runner.set_caps(meta["caps"][self.peers.index])
        self._saved = None  # consumed: from here on the learn runs on
        return state

    # ------------------------------------------------------------------ writing
    def set_selection(self, sel: SelectionState | None) -> None:
        """The selection state that later checkpoints carry."""
        self._selection = sel

    def save(self, state: EMState) -> None:
        """Write the checkpoint after an EM iteration, atomically (process 0 of a distributed
        learn, with every process's padded sizes)."""
        caps = self.peers.gather({"caps": self.runner.caps(), "round_caps": self._round_caps})
        if not self.peers.writes:
            return
        arrays, em_meta = _state_arrays(state)
        meta: dict[str, Any] = {
            "kind": CHECKPOINT_KIND,
            "format_version": _VERSION,
            "digest": self.digest,
            "stage": self.stage,
            "round": self.round,
            "caps": [c["caps"] for c in caps],
            "round_caps": [c["round_caps"] for c in caps],
            "em": em_meta,
            "selection": None,
        }
        if self._selection is not None:
            sel = self._selection
            marr, mmeta = sel.best.to_arrays_json()
            arrays.update({f"sel.{k}": v for k, v in marr.items()})
            arrays["sel_value"] = np.asarray(sel.best_value, dtype=np.float64)
            meta["selection"] = {
                "model": mmeta,
                "m": sel.m,
                "round": sel.round,
                "m_cap": sel.m_cap,
                "capacity": [int(c) for c in sel.capacity],
            }
        save_arrays_json(self.path, arrays, meta)
