"""The nearest surface: the refinement's energies, normal equations, quasi-Newton steps,
mixed precision, damping, stopping rules and the :class:`Refiner` (:mod:`.refiner`).
Imports :mod:`solver.core`, :mod:`solver.linalg` and :mod:`solver.mesh`.

``solver.refine`` keeps the names it had as one module."""

from .refiner import (
    ANGLE_WEIGHT,
    AREA_FLOOR,
    AREA_WEIGHT,
    DEFORM_ANGLE_WEIGHT,
    FORMS_TOLERANCE,
    HARD_FRAME_WEIGHT,
    PATTERN_CACHE_BYTES,
    FormEnergy,
    FormTargets,
    GaussNewtonSystem,
    Handles,
    Refinement,
    Refiner,
    StepRules,
    StopReason,
    StopRules,
    clear_pattern_cache,
    factor_precision,
    form_residuals,
    form_weights,
    hinge_angles,
    hinges,
    pattern_cache_info,
    refine,
    reproduces,
    signed_areas,
)

__all__ = ["ANGLE_WEIGHT", "AREA_FLOOR", "AREA_WEIGHT", "DEFORM_ANGLE_WEIGHT", "FORMS_TOLERANCE",
           "HARD_FRAME_WEIGHT", "PATTERN_CACHE_BYTES", "FormEnergy", "FormTargets",
           "GaussNewtonSystem", "Handles", "Refinement", "Refiner", "StepRules", "StopReason",
           "StopRules", "clear_pattern_cache", "factor_precision", "form_residuals",
           "form_weights", "hinge_angles", "hinges", "pattern_cache_info", "refine",
           "reproduces", "signed_areas"]
