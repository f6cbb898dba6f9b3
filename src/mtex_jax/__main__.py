"""``python -m mtex_jax`` is the ``mtex`` command."""

import sys

from .cli import main

sys.exit(main())
