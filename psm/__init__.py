"""Phase Space Model (PSM): learn a motion from ONE demonstration and reproduce it towards moving
goals, through perturbations and around obstacles (see ``docs/psm.md``).

Pure numpy/scipy: no bus, camera or robot needed.

>>> from psm import PhaseSpaceModel
"""

from psm import pstf
from psm.controller import PSMController
from psm.errors import (
    DemonstrationError,
    ModelFileError,
    ParameterError,
    PSMError,
    ShapeError,
)
from psm.model import ModelParameters, PhaseSpaceModel, Rollout, ViaPoints

__all__ = [
    "DemonstrationError",
    "ModelFileError",
    "ModelParameters",
    "PSMController",
    "PSMError",
    "ParameterError",
    "PhaseSpaceModel",
    "Rollout",
    "ShapeError",
    "ViaPoints",
    "pstf",
]
