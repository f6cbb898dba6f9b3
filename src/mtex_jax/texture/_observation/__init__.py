"""Observation models of textons, one module each behind :class:`ObservationModel`
(design §2.2, §10.3). Adding a model: a module implementing the protocol and one line in
:data:`OBSERVATION_MODELS`."""

from .base import ObservationModel as ObservationModel
from .full import FullObservation as FullObservation
from .paper import PaperObservation as PaperObservation
from .residual import ResidualObservation as ResidualObservation
from .tied import TiedObservation as TiedObservation

#: The registry: name (``Texton.observation``, ``LearnConfig.observation``) → model.
OBSERVATION_MODELS: dict[str, ObservationModel] = {
    m.name: m
    for m in (PaperObservation(), ResidualObservation(), FullObservation(), TiedObservation())
}


def observation_model(name: object) -> ObservationModel:
    """The registered observation model called ``name``; ``ValueError`` naming the models
    otherwise."""
    model = OBSERVATION_MODELS.get(name) if isinstance(name, str) else None
    if model is None:
        raise ValueError(f"observation must be one of {tuple(OBSERVATION_MODELS)}, got {name!r}")
    return model


__all__ = [
    "OBSERVATION_MODELS",
    "FullObservation",
    "ObservationModel",
    "PaperObservation",
    "ResidualObservation",
    "TiedObservation",
    "observation_model",
]
