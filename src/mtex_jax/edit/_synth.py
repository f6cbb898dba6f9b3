"""``synthesize(..., clean=True)``: the texture's synthesis, optionally cleaned (design §6.6)."""

from __future__ import annotations

from typing import Any

from ..motion import ContactModel
from ..texture import Synthesis, synthesize as _texture_synthesize
from ._clean import clean as _clean, contacts_of

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
    key segments), cleaned with the training clips' contact model: ``contacts`` when given,
    else the one the texture carries (``MotionTexture.contacts``, fitted by
    :func:`~mtex_jax.texture.learn` on the clips it learned from), so
    ``synthesize(key, tex, n_frames=1200, clean=True)`` needs nothing else.

    Args:
        key: PRNG key (or ``None`` for the zero-noise synthesis), as for the texture's.
        texture: the motion texture.
        *args: passed to :func:`mtex_jax.texture.synthesize`.
        **kwargs: passed to :func:`mtex_jax.texture.synthesize`.
        clean: clean the synthesis (remove foot skating and floor penetration).
        contacts: a contact model overriding the texture's (a
            :class:`~mtex_jax.motion.ContactModel` fitted on the training clips, see
            :func:`~mtex_jax.edit.load_contacts`).

    Raises:
        ValueError: ``contacts`` without ``clean=True``; ``clean=True`` on a texture that
            carries no contact model (learned from observation arrays) without ``contacts``.
    """
    if not clean:
        if contacts is not None:
            raise ValueError("contacts is only used with clean=True")
        return _texture_synthesize(key, texture, *args, **kwargs)
    cm = contacts_of(texture, contacts)  # before the synthesis: fail fast
    syn = _texture_synthesize(key, texture, *args, **kwargs)
    res = _clean(texture, syn, cm, loglik=False)
    return Synthesis(
        Y=res.Y,
        path=syn.path,
        lengths=syn.lengths,
        starts=syn.starts,
        key_segments=syn.key_segments,
        motion=res.motion,
    )
