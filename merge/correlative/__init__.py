"""A topography and an SEM image of one place, brought together: the secondary-electron
contrast a topography makes (:mod:`.contrast`), its registration onto an SEM image
(:mod:`.register`), and the masked correlation both use (:mod:`.correlate`). Pure: arrays and
maps in, transforms out."""

from merge.correlative.contrast import se_features
from merge.correlative.register import (
    Registration,
    RegistrationError,
    SEMView,
    Similarity,
    register_to_sem,
)

__all__ = [
    "Registration",
    "RegistrationError",
    "SEMView",
    "Similarity",
    "register_to_sem",
    "se_features",
]
