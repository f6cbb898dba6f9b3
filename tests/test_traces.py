"""The trace counter of the tests sees a retrace and nothing else."""

import jax
import jax.numpy as jnp

from traces import count_traces


def test_count_traces_sees_a_new_shape_and_not_a_cache_hit():
    @jax.jit
    def kernel_under_count(x):
        return jnp.sin(x) * 2.0

    kernel_under_count(jnp.ones(3))
    with count_traces() as seen:
        kernel_under_count(jnp.zeros(3))  # same shape: cached
    assert seen["kernel_under_count"] == 0
    with count_traces() as seen:
        kernel_under_count(jnp.zeros(4))  # new shape: traced again
    assert seen["kernel_under_count"] == 1
