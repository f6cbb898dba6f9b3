"""Run a test script in a fresh Python process that has several XLA CPU devices (the device
count is fixed when JAX starts, so it cannot change inside the test process)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

from jax_cache import child_env


def run_with_cpu_devices(
    script: str, marker: str, *, n: int = 2, timeout: int = 900, **env: str
) -> str:
    """Run ``script`` (dedented) with ``n`` CPU devices and ``TESTS_DIR`` plus ``env`` set
    (and the persistent compilation cache of this process, :mod:`jax_cache`);
    assert that it exits 0 and prints ``marker``; return its standard output."""
    full = child_env(**env)  # with this process's compilation cache
    full["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={n}"
    full["TESTS_DIR"] = os.path.dirname(__file__)
    r = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        env=full,
        timeout=timeout,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert marker in r.stdout, r.stdout[-2000:]
    return r.stdout
