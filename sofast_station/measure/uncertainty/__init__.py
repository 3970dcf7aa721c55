"""Expanded uncertainty (k = 2) of every reported figure, and its budget (docs/uncertainty.md).

Two parts, combined per the GUM (root sum of squares of standard-uncertainty contributions, times the
coverage factor 2): the **random** part, what changes from capture to capture (the capture's own intensity
noise through positions, slopes and fits; the corners' noise; the frames' brightness), and the
**systematic** part, each figure's sensitivity to each station input by finite differences of the whole
reduction. The package's parts, one idea each: ``inputs.py`` (the inputs, their standard uncertainties,
the budget's rows and figures), ``systematic.py`` (the sensitivities), ``intensity_noise.py`` (the noise
the capture explains), ``corner_pose.py`` (the corner pose's Monte Carlo), ``capture_evidence.py`` (what
each capture says about its own inputs) and ``budget.py`` (the combination and the budget table;
:func:`uncertainty_figures` is the entry point). Pure functions: numpy and records in, numpy and dicts out.
"""

from .budget import budget_table, combine, uncertainty_figures
from .capture_evidence import (capture_scales, display_response_u, frame_brightness_dn, pooled_frame_brightness,
                               small_sample_factor)
from .corner_pose import POSE_DRAWS, POSE_GROUPS, POSE_PATHS, pose_draws, pose_monte_carlo, solve_poses_batch
from .inputs import (COVERAGE_FACTOR, SCALAR_PATHS, Input, InputUncertainties, budget_inputs, get_path,
                     lut_phase_error_rad, path_name, small_motion)
from .intensity_noise import NoisePropagation, noise_propagation, pixel_noise_dn
from .systematic import Sensitivities, sensitivities, sensitivity_key

__all__ = ["COVERAGE_FACTOR", "POSE_DRAWS", "POSE_GROUPS", "POSE_PATHS", "SCALAR_PATHS", "Input", "InputUncertainties",
           "NoisePropagation", "Sensitivities", "budget_inputs", "budget_table", "capture_scales", "combine",
           "display_response_u", "frame_brightness_dn", "get_path", "lut_phase_error_rad", "noise_propagation",
           "path_name", "pixel_noise_dn", "pooled_frame_brightness", "pose_draws", "pose_monte_carlo", "sensitivities",
           "sensitivity_key", "small_motion", "small_sample_factor", "solve_poses_batch", "uncertainty_figures"]
