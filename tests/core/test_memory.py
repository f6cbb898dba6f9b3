"""core.check_memory (issue 57): work is measured before it runs and refused with both figures
when it needs more memory than the process can allocate; the measure is XLA's own analysis."""

from __future__ import annotations

import resource

import jax
import jax.numpy as jnp
import pytest

from mtex_jax.core import available_memory, check_memory, program_bytes


def test_program_bytes_is_the_compiled_programs_arguments_outputs_and_temporaries():
    n = 1 << 20
    compiled = jax.jit(lambda x: jnp.outer(x, x[:8]).sum(axis=1)).lower(jnp.ones(n)).compile()
    need = program_bytes(compiled)
    itemsize = jnp.ones(1).dtype.itemsize
    assert need >= 2 * n * itemsize  # the argument and the output at least
    assert need <= 20 * n * itemsize  # and not the materialised n × 8 product many times


def test_check_memory_names_what_it_needs_and_what_is_left():
    have = available_memory()
    assert have is None or have > 0
    check_memory(1, "one byte")  # passes
    with pytest.raises(ValueError, match=r"a huge thing needs about 8192\.00 GiB of memory"):
        check_memory(8 << 40, "a huge thing")


def test_the_address_space_limit_is_counted():
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    before = available_memory()
    with open("/proc/self/status") as fh:
        vm = next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith("VmSize:"))
    cap = vm + (256 << 20)
    if hard != resource.RLIM_INFINITY:
        cap = min(cap, hard)  # a soft limit may not exceed the hard one
    resource.setrlimit(resource.RLIMIT_AS, (cap, hard))
    try:
        left = available_memory()
        assert left is not None and left <= 256 << 20
        assert before is None or left <= before
        with pytest.raises(ValueError, match=r"more than the 0\.\d\d GiB this process can"):
            check_memory(1 << 30, "a gibibyte")
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
