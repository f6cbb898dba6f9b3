"""Observation models of textons, one module each behind :class:`ObservationModel`
(design §2.2, §10.3). A model is chosen by passing its member (``ResidualObservation()``);
names are for the CLI and model files. Adding a model: a module with its member and one line
in :data:`OBSERVATION_MODELS`."""

from typing import Any

from .base import MEMBER_FIELDS as MEMBER_FIELDS, ObservationModel as ObservationModel
from .full import FullObservation as FullObservation
from .paper import PaperObservation as PaperObservation
from .residual import ResidualObservation as ResidualObservation
from .tied import TiedObservation as TiedObservation

#: The registry: name (the CLI's ``--observation``, ``LearnConfig.observation``, a model
#: file's JSON) → the member without parameters that chooses the model.
OBSERVATION_MODELS: dict[str, ObservationModel] = {
    m.name: m
    for m in (PaperObservation(), ResidualObservation(), FullObservation(), TiedObservation())
}


def observation_model(name: object) -> ObservationModel:
    """The registered observation model called ``name`` (a member is returned as it is);
    ``ValueError`` naming the models otherwise."""
    if isinstance(name, ObservationModel):
        return name
    model = OBSERVATION_MODELS.get(name) if isinstance(name, str) else None
    if model is None:
        raise ValueError(f"observation must be one of {tuple(OBSERVATION_MODELS)}, got {name!r}")
    return model


def check_observation(model: Any, where: str = "observation") -> ObservationModel:
    """``model`` if it is an observation model's member; ``TypeError`` saying how to mend it
    otherwise (a name is spelled only at the CLI and in files)."""
    if isinstance(model, ObservationModel):
        return model
    if isinstance(model, str) and model in OBSERVATION_MODELS:
        member = type(OBSERVATION_MODELS[model]).__name__
        raise TypeError(
            f"{where} takes an observation model's member, e.g. {member}() "
            f"(observation_model({model!r})), not the name {model!r}"
        )
    names = ", ".join(f"{type(m).__name__}()" for m in OBSERVATION_MODELS.values())
    raise TypeError(f"{where} must be one of {names}, got {model!r}")


__all__ = [
    "MEMBER_FIELDS",
    "OBSERVATION_MODELS",
    "FullObservation",
    "ObservationModel",
    "PaperObservation",
    "ResidualObservation",
    "TiedObservation",
    "check_observation",
    "observation_model",
]
