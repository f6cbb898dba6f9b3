"""``mtex learn --distributed``: this process as one of a multi-process learn (the runtime of
``jax.distributed``), set up from flags or environment variables."""

from __future__ import annotations

import argparse
import os
from typing import Any

__all__ = ["RECIPE", "add_arguments", "agree", "share", "start"]

_ENV = {
    "coordinator": "MTEX_COORDINATOR",
    "num_processes": "MTEX_NUM_PROCESSES",
    "process_id": "MTEX_PROCESS_ID",
    "local_devices": "MTEX_LOCAL_DEVICES",
}

RECIPE = """\
distributed learning (--distributed): start one process per host, or one per GPU/TPU, each
with the same options; every process reads its own clips (or, with --split-clips, its share
of one list) and all of them end with the same model, which process 0 writes.
  coordinator   host:port of process 0, reachable from every process (MTEX_COORDINATOR)
  processes     how many processes in all (MTEX_NUM_PROCESSES)
  process id    0 .. processes-1, unique per process (MTEX_PROCESS_ID)
  devices       this process's local devices, e.g. 0 for one process per GPU
                (MTEX_LOCAL_DEVICES; default: all of the host's)
Without coordinator, processes and id, JAX finds them from the cluster launcher (SLURM,
Open MPI, Cloud TPU). On CPU the collectives are gloo's, over TCP. Two processes on one
machine:
  mtex learn --distributed --coordinator 127.0.0.1:12355 --num-processes 2 \\
      --process-id 0 a.bvh b.bvh -o model.npz &
  mtex learn --distributed --coordinator 127.0.0.1:12355 --num-processes 2 \\
      --process-id 1 c.bvh d.bvh -o model.npz
"""


def add_arguments(s: argparse.ArgumentParser) -> None:
    """The ``--distributed`` options of ``mtex learn``."""
    g = s.add_argument_group("distributed learning (see the end of this help)")
    g.add_argument(
        "--distributed",
        action="store_true",
        help="be one process of a multi-process learn (jax.distributed)",
    )
    g.add_argument("--coordinator", default=None, help="host:port of process 0")
    g.add_argument("--num-processes", type=int, default=None, help="processes in all")
    g.add_argument("--process-id", type=int, default=None, help="this process, 0-based")
    g.add_argument(
        "--local-devices",
        default=None,
        help="comma-separated local device ids for this process (default: all)",
    )
    g.add_argument(
        "--split-clips",
        action="store_true",
        help="every process is given the same clips; process i learns from its contiguous share",
    )


def _setting(args: argparse.Namespace, name: str) -> str | None:
    value = getattr(args, name)
    if value is None:
        value = os.environ.get(_ENV[name]) or None
    return None if value is None else str(value)


def _int(name: str, text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"--{name.replace('_', '-')} must be an integer, got {text!r}") from None


def start(args: argparse.Namespace) -> tuple[int, int]:
    """Initialise ``jax.distributed`` (before any other use of JAX) from the flags, else the
    environment; returns ``(process_id, process_count)``."""
    import jax

    coord = _setting(args, "coordinator")
    n_text = _setting(args, "num_processes")
    pid_text = _setting(args, "process_id")
    dev_text = _setting(args, "local_devices")
    given = [v is not None for v in (coord, n_text, pid_text)]
    if any(given) and not all(given):
        missing = [
            f"--{k.replace('_', '-')} ({_ENV[k]})"
            for k, v in zip(("coordinator", "num_processes", "process_id"), given, strict=True)
            if not v
        ]
        raise ValueError(
            f"--distributed: give all of coordinator, processes and id; missing {missing}"
        )
    kwargs: dict[str, Any] = {}
    if all(given):
        assert coord is not None and n_text is not None and pid_text is not None
        n = _int("num_processes", n_text)
        pid = _int("process_id", pid_text)
        if n < 1 or not 0 <= pid < n:
            raise ValueError(f"--distributed: process id {pid} is not in 0..{n - 1}")
        kwargs = dict(coordinator_address=coord, num_processes=n, process_id=pid)
    if dev_text is not None:
        kwargs["local_device_ids"] = [_int("local_devices", d) for d in dev_text.split(",")]
    # the program (not the library) chooses the runtime: gloo collectives between CPU processes
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(**kwargs)
    if "num_processes" in kwargs and jax.process_count() != kwargs["num_processes"]:
        raise ValueError(
            f"--distributed: {jax.process_count()} processes joined, expected "
            f"{kwargs['num_processes']}"
        )
    return jax.process_index(), jax.process_count()


def share(items: list[str], pid: int, n: int) -> list[str]:
    """Process ``pid``'s contiguous share of ``items`` (in order, so that the processes' clips
    in process order are ``items``)."""
    return items[pid * len(items) // n : (pid + 1) * len(items) // n]


def agree(error: BaseException | None) -> None:
    """A collective check before learning: if any process failed (e.g. reading its clips),
    every process stops with an error instead of waiting for it."""
    import numpy as np
    from jax.experimental import multihost_utils

    flags = np.asarray(multihost_utils.process_allgather(np.asarray([error is not None])))
    if error is not None:
        raise error
    bad = np.nonzero(flags.reshape(-1))[0]
    if bad.size:
        raise ValueError(f"--distributed: process {int(bad[0])} failed (see its output)")
