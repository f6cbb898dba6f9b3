"""``synthesize(..., clean=True)``: the texture's synthesis, optionally cleaned."""

from __future__ import annotations

from typing import Any

from ..metrics import ContactModel
from ..texture import Synthesis, synthesize as _texture_synthesize
from ._clean import clean as _clean

__all__ = ["synthesize"]


def synthesize(
    key: Any,
    texture: Any,
    *args: Any,
    clean: bool = False,
    contacts: ContactModel | None = None,
    **kwargs: Any,
) -> Synthesis:
    """:func:`mtex_jax.texture.synthesize`, then (``clean=True``) :func:`mtex_jax.edit.clean`.

    With ``clean=False`` this is exactly the texture's synthesis. With ``clean=True`` the
    returned :class:`Synthesis` has the cleaned ``Y`` and ``motion`` (same path, lengths and
    key segments); ``contacts`` (a :class:`~mtex_jax.metrics.ContactModel` fitted on the
    training clips, see :func:`~mtex_jax.edit.load_contacts`) is then required.

    Args:
        key: PRNG key (or ``None`` for the zero-noise synthesis), as for the texture's.
        texture: the motion texture.
        *args: passed to :func:`mtex_jax.texture.synthesize`.
        **kwargs: passed to :func:`mtex_jax.texture.synthesize`.
        clean: clean the synthesis (remove foot skating and floor penetration).
        contacts: the training clips' contact model (required with ``clean=True``).
    """
    syn = _texture_synthesize(key, texture, *args, **kwargs)
    if not clean:
        if contacts is not None:
            raise ValueError("contacts is only used with clean=True")
        return syn
    if contacts is None:
        raise ValueError(
            "clean=True needs contacts: a ContactModel fitted on the training clips "
            "(mtex_jax.metrics.fit_contacts, or mtex_jax.edit.load_contacts)"
        )
    res = _clean(texture, syn, contacts, loglik=False)
    return Synthesis(
        Y=res.Y,
        path=syn.path,
        lengths=syn.lengths,
        starts=syn.starts,
        key_segments=syn.key_segments,
        motion=res.motion,
    )
