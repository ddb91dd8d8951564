"""Diagnosis: name the effects that separate a measurement from the ideal model.

The registry of physical effects and artefacts (:mod:`.effects`); the model-selection engine
that fits (:mod:`.fitting`), scores and names them (:mod:`.engine`) on the noise floor of the data (:mod:`.noise`);
the two problems it solves, height maps (:mod:`.heights`) and PSF stacks (:mod:`.psf`); the
window with most structure (:mod:`.window`), residual breakdowns (:mod:`.breakdown`), where an unexplained residual lives (:mod:`.locate`), figures
(:mod:`.plots`); and the hidden-effect generator used by the tests and the demo
(:mod:`.synthetic`). The public API is re-exported here.
"""

from metrology.diagnosis.breakdown import binned, radial_psd
from metrology.diagnosis.effects import (Effect, EffectError, Parameter, effects_for, get_effect, register_effect,
                                         unregister_effect)
from metrology.diagnosis.engine import DEFAULT_THRESHOLD, Diagnosis, Problem, Step, bic_eff, run_diagnosis
from metrology.diagnosis.locate import locate_residual
from metrology.diagnosis.heights import (HeightProblem, diagnose_heights, diagnose_measurement,
                                         signed_edge_distance_m)
from metrology.diagnosis.noise import NoiseEstimate, estimate_noise
from metrology.diagnosis.psf import PsfProblem, PsfRenderer, diagnose_psf, psf_forward
from metrology.matching.window import busiest_window

__all__ = ["DEFAULT_THRESHOLD", "Diagnosis", "Effect", "EffectError", "HeightProblem", "NoiseEstimate", "Parameter",
           "Problem", "PsfProblem", "PsfRenderer", "Step", "bic_eff", "binned", "busiest_window", "diagnose_heights",
           "diagnose_measurement", "diagnose_psf", "effects_for", "estimate_noise", "get_effect", "locate_residual",
           "psf_forward", "radial_psd", "register_effect", "run_diagnosis", "signed_edge_distance_m",
           "unregister_effect"]
