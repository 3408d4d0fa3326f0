"""The old import path of the model-rollout sampler: :mod:`mixedrl.samplers` (re-exported)."""

from mixedrl.samplers import SAMPLER_CLASSES, ModelStateSampler, course_starts, has_course

__all__ = ["ModelStateSampler", "SAMPLER_CLASSES", "course_starts", "has_course"]
