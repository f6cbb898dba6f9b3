"""How much memory a program needs and how much this process may still take (issue 57).

A generator whose size the user chooses (particles, frames) measures its compiled program
before it runs it: XLA's memory analysis gives the bytes of the arguments, the outputs and the
temporaries (:func:`program_bytes`), and :func:`check_memory` refuses, with a ``ValueError``
naming both figures, a program that needs more than the machine's free memory or what the
address-space limit (``RLIMIT_AS``, ``ulimit -v``) leaves the process.
"""

from __future__ import annotations

from typing import Any

__all__ = ["available_memory", "check_memory", "program_bytes"]


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _address_space_left() -> int | None:
    try:
        import resource
    except ImportError:  # not on POSIX
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmSize:"):
                    return max(0, soft - int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        return None
    return None


def available_memory() -> int | None:
    """Bytes this process may still allocate: the least of the machine's available memory
    (``MemAvailable``) and what ``RLIMIT_AS`` leaves beyond the process's address space;
    ``None`` where neither is known."""
    known = [b for b in (_meminfo_available(), _address_space_left()) if b is not None]
    return min(known) if known else None


def program_bytes(compiled: Any) -> int:
    """The bytes a compiled program holds while it runs: arguments, outputs and temporaries,
    from XLA's memory analysis (``compiled`` a ``jax.stages.Compiled``)."""
    ma = compiled.memory_analysis()
    return int(ma.argument_size_in_bytes + ma.output_size_in_bytes + ma.temp_size_in_bytes)


def check_memory(need: int, what: str) -> None:
    """Refuse work that needs more memory than :func:`available_memory`.

    Args:
        need: the bytes the work needs.
        what: the work, for the message (``"track: 1,000,000 particles over 150 frames"``).

    Raises:
        ValueError: naming ``what``, the memory it needs and the memory available.
    """
    have = available_memory()
    if have is not None and need > have:
        raise ValueError(
            f"{what} needs about {need / 2**30:.2f} GiB of memory (the compiled program's "
            f"arguments, outputs and temporaries), more than the {have / 2**30:.2f} GiB this "
            "process can still allocate; ask for less"
        )
