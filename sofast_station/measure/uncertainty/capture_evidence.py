"""What each capture's own evidence says about the inputs that change from capture to capture: the
frame-to-frame brightness (pooled over the recent captures of a geometry and recipe), the display
response's phase error, and the corners' location noise, as factors on the cached sensitivities.
"""

from __future__ import annotations

import numpy as np

from ..phase import MAX_NOISE_SAMPLES, phase_error_from_harmonic
from ..stats import median
from .inputs import InputUncertainties
from .systematic import Sensitivities


def small_sample_factor(dof: int) -> float:
    """Standard deviation of a Type A quantity estimated from *dof* degrees of freedom, per unit estimate.

    A standard deviation s estimated from nu observations leaves the quantity t-distributed about its
    estimate, with standard deviation s sqrt(nu / (nu - 2)) (GUM Supplement 1, 6.4.9): for the few
    fringe sets of a capture (4 with two periods per axis) that is 1.41 s, without which a k = 2 interval
    covers about 88 % instead of 95 %. At most sqrt(3) (nu = 3) when nu is smaller.
    """
    nu = max(int(dof), 3)
    return float(np.sqrt(nu / (nu - 2.0)))


#: Captures whose frame-brightness estimates are pooled (the most recent ones of a geometry and recipe).
FRAME_POOL_CAPTURES = 50
#: A capture whose own frame-brightness estimate is beyond this quantile of the pooled one (F test) uses
#: its own: the room light changed, or this capture was disturbed.
FRAME_POOL_QUANTILE = 0.99


def frame_brightness_dn(reduction) -> tuple[float, int]:
    """The capture's own frame-to-frame brightness noise sigma_f (DN) and its degrees of freedom: each
    set's mean consistency residual I0 + I2 - I1 - I3 has variance 4 sigma_f^2 (one value per set).

    Less the display's static harmonic where the residuals' fit found one (``harmonic_offsets_dn`` of the
    capture's :class:`~sofast_station.measure.phase.FrameNoise`): a facet that sees a short stretch of a
    coarse fringe sees nearly one phase, and a display response left a little nonlinear then shifts that
    set's mean by the same amount in every capture. Counted as brightness noise it made sigma_f 0.8 DN
    instead of 0.05 on a population dish station with its display at gamma 2.227 (the table's 2.2) and the
    room light steady, and the U of the slope RMS values, the focal lengths and the twist about twice their
    errors' spread (the population study's dish stations: RMS of error / (U / 2) 0.5-0.6)."""
    offsets = getattr(reduction.phases, "set_offsets_dn", {}) or {}
    allsets = np.array([v for a in ("x", "y") for v in offsets.get(a, [])], float)
    if not allsets.size:
        return 0.0, 0
    noise = getattr(reduction.phases, "noise", None)
    static = np.asarray(getattr(noise, "harmonic_offsets_dn", ()) or (), float)
    if static.shape == allsets.shape and np.all(np.isfinite(static)):
        allsets = allsets - static
    return float(np.sqrt(np.mean(np.square(allsets)) / 4.0)), int(allsets.size)


def pooled_frame_brightness(own_dn: float, dof: int, pool) -> dict:
    """The frame-brightness noise a capture's uncertainty uses: pooled over the recent captures of the same
    geometry and recipe (GUM 4.2.4: a pooled variance of a measurement under statistical control), or the
    capture's own when it is significantly larger (F test at :data:`FRAME_POOL_QUANTILE`).

    *pool* (a deque, or None for no pooling) receives this capture's (sum of squares, dof). The value used
    is widened by :func:`small_sample_factor` of its degrees of freedom.

    Returns
    -------
    dict
        ``sigma_dn`` (used, widened), ``own_dn``, ``pooled_dn``, ``dof`` (of the value used), ``captures``
        (in the pool), ``source`` ("pooled" or "own").
    """
    own = {"sigma_dn": own_dn * small_sample_factor(dof), "own_dn": own_dn, "pooled_dn": None, "dof": dof,
           "captures": 1, "source": "own"}
    if pool is None or dof == 0:
        return own
    pool.append((own_dn ** 2 * dof, dof))
    n = sum(d for _, d in pool)
    pooled = float(np.sqrt(sum(ss for ss, _ in pool) / n))
    if len(pool) == 1:
        return own | {"pooled_dn": pooled}
    # The F distribution's quantile (scipy.stats' f.ppf computes this very function; scipy.stats itself
    # takes a second to import, which the first pooled capture paid)
    from scipy.special import fdtri  # lazy: scipy.special costs ~0.5 s at import; only a pooled capture needs it
    limit = float(fdtri(dof, max(n - dof, 1), FRAME_POOL_QUANTILE))
    if pooled > 0 and own_dn ** 2 / pooled ** 2 > limit:
        return own | {"pooled_dn": pooled, "captures": len(pool)}
    return {"sigma_dn": pooled * small_sample_factor(n), "own_dn": own_dn, "pooled_dn": pooled, "dof": n,
            "captures": len(pool), "source": "pooled"}


def display_response_u(reduction, inputs: InputUncertainties) -> dict:
    """Standard uncertainty (rad) of the display response's phase error for this capture, from the
    capture's own evidence (docs/uncertainty.md, "display response").

    A response left nonlinear puts a second harmonic, correlated with the phase, into every four-step
    residual; :func:`~sofast_station.measure.phase.frame_noise` fits it over all sets (ratio r to the
    fringe's amplitude) and turns it into the largest four-step phase error E it gives for a power-law
    response (:func:`~sofast_station.measure.phase.phase_error_from_harmonic`). The fit's own standard
    uncertainty: each harmonic coefficient of the residual ``b (beta cos 2 phi + gamma sin 2 phi)``,
    fitted to N samples with residual noise 2 sigma (four frames of noise sigma), has standard deviation
    ``2 sigma / (b sqrt(N / 2))``, and r = |(beta, gamma)| / 4, so ``u(r) = sigma / (2 b sqrt(N / 2))``
    and ``u(E) = |dE/dr| u(r)``. Where the capture's coarse and fine sets show the phase error directly
    (:func:`~sofast_station.measure.phase.phase_error_between_periods`: any shape of response), E and
    u(E) are theirs. The value used is ``sqrt(E^2 + u(E)^2)``: the phase error is not corrected, so its
    estimate counts in full, together with the estimate's uncertainty.

    The second harmonic shows a smooth miss of the response (a gamma not quite inverted), not the rounding
    of the fringes to whole 8-bit commands, whose 4-times-phase part the radiometric record in force
    states (``inputs.response_record_rad``, :func:`lut_phase_error_rad`): it is added in quadrature.

    ``[uncertainty] response_phase_rad`` is used when neither the capture (no four-step sets) nor a record
    says anything, and 0 there leaves the display response out of the budget.

    Returns
    -------
    dict
        ``u_rad`` (used), ``source`` ("capture", "capture and record", "record", "default" or "off"), and
        for a capture's evidence ``estimate_rad`` (E), ``estimate_u_rad`` (u(E)) and ``harmonic_ratio``
        (signed r); ``record_rad`` when a record's value is in it.
    """
    if inputs.response_phase_rad <= 0 or not getattr(reduction.phases, "four_step", True):
        # (a capture without four-step sets, a fixed pattern's, has no phase for a response to shift)
        return {"u_rad": 0.0, "source": "off"}
    fn = getattr(reduction.phases, "noise", None)
    ratio = getattr(fn, "signed_harmonic_ratio", None)
    sigma = getattr(fn, "frame_noise_dn", None)
    offsets = getattr(reduction.phases, "set_offsets_dn", None) or {}
    n_sets = sum(len(offsets.get(a, [])) for a in ("x", "y"))
    record = inputs.response_record_rad
    mods = []
    if ratio is not None and sigma is not None and n_sets and np.isfinite(ratio):
        ok = reduction.rays.ok
        mods = [np.asarray(reduction.phases.finest_modulation_dn[a])[ok] for a in ("x", "y")]
    if not mods or mods[0].size == 0:
        if record is not None:
            return {"u_rad": float(record), "source": "record", "record_rad": float(record)}
        return {"u_rad": float(inputs.response_phase_rad), "source": "default"}
    b = float(np.sqrt(np.mean(np.concatenate(mods) ** 2)))
    n = min(int(reduction.region.idx.size) * n_sets, MAX_NOISE_SAMPLES)
    u_ratio = float(sigma) / (2.0 * max(b, 1e-9) * np.sqrt(max(n, 2) / 2.0))
    estimate = float(fn.phase_error_rad)
    if getattr(fn, "phase_error_u_rad", None) is not None:
        u_estimate = float(fn.phase_error_u_rad)        # measured between the period sets, with its fit's u
    else:
        h = max(u_ratio, 1e-6)
        slope = abs(phase_error_from_harmonic(abs(ratio) + h) - phase_error_from_harmonic(abs(ratio))) / h
        u_estimate = slope * u_ratio
    out = {"u_rad": float(np.hypot(estimate, u_estimate)), "source": "capture", "estimate_rad": estimate,
           "estimate_u_rad": float(u_estimate), "harmonic_ratio": float(ratio)}
    if record is not None:
        # The two are different errors (a smooth miss of the response, the rounding to whole commands).
        out.update(u_rad=float(np.sqrt(out["u_rad"] ** 2 + record ** 2)), source="capture and record",
                   record_rad=float(record))
    return out


def capture_scales(reduction, sens: Sensitivities, inputs: InputUncertainties,
                   frame_sigma_dn: float | None = None, response_u_rad: float | None = None) -> np.ndarray:
    """Per budget row, the factor by which this capture's own estimate scales the cached sensitivity
    (1 for the systematic rows).

    * corner location: each corner coordinate's standard uncertainty from the sides' fits (the diagonal
      of ``CornerPoseResult.corner_cov_px2``; the median ``corner_sigma_px`` without it) over the
      ``corner_px`` the sensitivities were computed at (:func:`combine` also uses the correlations);
    * frame-to-frame brightness: the phase-error amplitude sigma_f / (sqrt(2) b) of each quadrature, with
      sigma_f the frames' brightness noise from the sets' mean consistency residuals
      (I0 + I2 - I1 - I3 has variance 4 sigma_f^2) and b the median finest-set modulation of the axis,
      over the reference amplitude; sigma_f is *frame_sigma_dn* when given (:func:`pooled_frame_brightness`),
      else the capture's own times :func:`small_sample_factor` of its number of sets (it comes from that few
      values);
    * display response: *response_u_rad* (:func:`display_response_u`, the capture's own evidence) over
      ``response_phase_rad``, at which the sensitivities were computed; 1 when not given.
    """
    scales = np.ones(len(sens.inputs))
    sigma_c = getattr(reduction.pose, "corner_sigma_px", None)
    cov = getattr(reduction.pose, "corner_cov_px2", None)
    corner_rows = [i for i, inp in enumerate(sens.inputs) if inp.group == "corner location"]
    per_coordinate = None
    if cov is not None and cov.shape == (len(corner_rows), len(corner_rows)):
        per_coordinate = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if frame_sigma_dn is None:
        own, dof = frame_brightness_dn(reduction)
        sigma_f = own * small_sample_factor(dof)
    else:
        sigma_f = float(frame_sigma_dn)
    ok = reduction.rays.ok
    amp = {}
    if any(inp.group == "frame-to-frame brightness" for inp in sens.inputs):
        for a in ("x", "y"):
            b = float(median(reduction.phases.finest_modulation_dn[a][ok]))
            amp[a] = sigma_f / (np.sqrt(2.0) * max(b, 1e-9))
    for i, inp in enumerate(sens.inputs):
        if inp.group == "corner location" and per_coordinate is not None and inp.u > 0:
            scales[i] = per_coordinate[corner_rows.index(i)] / inp.u
        elif inp.group == "corner location" and sigma_c is not None and inp.u > 0:
            scales[i] = sigma_c / inp.u
        elif inp.group == "frame-to-frame brightness":
            scales[i] = amp[inp.name.split()[2]] / inp.u
        elif inp.group == "display response" and response_u_rad is not None and inp.u > 0:
            scales[i] = response_u_rad / inp.u
    return scales
