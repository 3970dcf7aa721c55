"""The argument types the ahead-of-time build of :mod:`.kernels` compiles each kernel for
(:mod:`sofast_station.build_kernels`; docs/performance.md).

One string per entry, one word per argument: an array as ``dtype:ndim layout`` (numpy's short dtype
codes: f8 float64, f4 float32, i8 int64, i4 int32, u1 uint8, u2 uint16, b1 bool; layout C, F or A for
any strides; a trailing ``r`` for a read-only array), a scalar as ``f8``, ``f4``, ``i8`` or ``bool``.
An entry whose kernel returns a value ends in its type: ``-> i8``, ``-> f8``, ``-> bool`` or a tuple of
those, ``-> (i8, f8)``; without one the kernel returns nothing. The build checks each against the type numba
infers (a wrong one stops it, naming the entry): declared, the build needs no JIT compile to learn it, and
numba's JIT warms its cache beside the build instead of before it (half a minute of setup-env).
These are the types the commands and the station call the kernels with (read from numba's cache of a
full test run); a call with other types is compiled by numba's JIT, as without a build
(:class:`.compiled.Kernel`). Kernels called only from other kernels are compiled into their callers and
need no entry.
"""

SIGNATURES: dict[str, list[str]] = {
    "_atan_into": [
        "f8:1C f8:1C",
    ],
    "_bilinear_into": [
        "f8:2C f8 f8 f8 f8:1C f8:1C f8:1C",
        "f8:2Cr f8 f8 f8 f8:1C f8:1C f8:1C",
    ],
    "_cleaned_into": [
        "f4:1C f4:1C f4:1C f4:1C bool f4:1C f4:1C f4 f4 f4:1C",
    ],
    "_consistency_into": [
        "f4:1C f4:1C f4:1C f4 f8:1C b1:1C -> (i8, f8)",
    ],
    "_count_labels_into": [
        "i4:1C i8:1C",
    ],
    "_cubic_sums_into": [
        "f8:1C f8:1C f8:1C f8:1C f8 f8 f8 i8 f8:2C",
    ],
    "_dot_centroids_into": [
        "u1:2C f8:2C f8 bool i8 f8:2C b1:1C f8:3C f8:1C f8:1C f8:1C",
        "u2:2C f8:2C f8 bool i8 f8:2C b1:1C f8:3C f8:1C f8:1C f8:1C",
    ],
    "_fill_holes_into": [
        "i4:2C i8 i8:1C b1:1C b1:2A",
        "i4:2C i8 i8:1C b1:1C b1:2C",
    ],
    "_gather_runs_into": [
        "u2:2C i8:1C i8:1C i8:1C u2:2C",
        "u1:2C i8:1C i8:1C i8:1C u1:2C",
    ],
    "_grid_sums_into": [
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8 f8 f8 f8:2C f8:2C f8:2C f8:2C f8:2C",
    ],
    "_grid_screen_into": [
        "f8:1C f8:1C f8:1C f8:1C f8:3C b1:2C f8 f8:2C f8:1C f8:2C",
        "f8:1C f8:1C f8:1C f8:1C f8:3C b1:2C f8 f8:2F f8:1C f8:2C",
    ],
    "_label_moments_into": [
        "i4:2C f8:2C",
    ],
    "_laplacian_counts_into": [
        "u1:2A b1:2A i8:1C -> i8",
        "u2:2A b1:2A i8:1C -> i8",
        "u1:2C b1:2C i8:1C -> i8",
        "u2:2C b1:2C i8:1C -> i8",
    ],
    "_lattice_walk_into": [
        "f8:2C i8 f8:2C f8 f8 f8:3C i8:2C",
    ],
    "_minus_models_into": [
        "f8:1C f8:2C f8:1C f8:2C f8:1C f8:1C",
    ],
    "_moved_into": [
        "f8:1C f8:1C f8:1C f8:2C f8:1C f8 bool f8:2C",
    ],
    "_noise_rows_into": [
        "f4:1C f4:1C f4:1C f4:1C bool i8 f8:2C f8:2C f8:1C",
        "f4:1C f4:1C f4:1C f8:1C bool i8 f8:2C f8:2C f8:1C",
    ],
    "_normal_slopes_into": [
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C",
    ],
    "_parabola_sums_into": [
        "f8:1A f8:1A f8:1A f8:1A f8 f8 i8 f8:2C",
        "f8:1C f8:1C f8:1C f8:1C f8 f8 i8 f8:2C",
    ],
    "_phase_counts_into": [
        "u2:2C f4:1C f4:1C f4:1C",
        "u1:2C f4:1C f4:1C f4:1C",
    ],
    "_reflect_blend_into": [
        "f8:1A f8:1A f8:1A f8:1A f8:1A f8:1A f8:2C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C -> i8",
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:2C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C -> i8",
    ],
    "_reflect_into": [
        "f8:1A f8:1A f8:1A f8:1A f8:1A f8:1A f8:2C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C",
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:2C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C",
    ],
    "_residuals_into": [
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C",
    ],
    "_reweight_sums_into": [
        "f8:1C f8:1C f8:1C f8:1C f8 f8 f8:1C f8:1C f8 f8 i8 f8:2C",
    ],
    "_solve_poses_into": [
        "f8:3C f8:2C f8:3C f8:2C f8:1C i8 f8 f8:3C f8:2C b1:1C",
    ],
    "_to_frame_every_into": [
        "f8:1A f8:1A f8:1A f8:2C f8:1C i8 f8:2C",
        "f8:1C f8:1C f8:1C f8:2C f8:1C i8 f8:2C",
        "f8:1C f8:1C f8:1C f8:2F f8:1C i8 f8:2C",
    ],
    "_unwrap_into": [
        "f4:2C f8:1C f8 bool f8 f8:1C bool f8:1C b1:1C -> (i8, i8, i8)",
        "f4:2C f8:1C f8 bool f8 f8:1Cr bool f8:1C b1:1C -> (i8, i8, i8)",
        "f8:2C f8:1C f8 bool f8 f8:1C bool f8:1C b1:1C -> (i8, i8, i8)",
        "f8:2C f8:1C f8 bool f8 f8:1Cr bool f8:1C b1:1C -> (i8, i8, i8)",
    ],
    "bisquare_into": [
        "f8:1C f8 f8:1C",
    ],
    "irls_bisquare": [
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8 i8 f8 f8 f8 f8 f8:1C -> (i8, f8)",
    ],
    "median_in_window": [
        "f8:1C f8 bool f8 f8 f8:1C -> (f8, bool)",
    ],
    "residuals_and_leverage": [
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C -> (f8, f8)",
    ],
    "sum_squares": [
        "f8:1C f8:1C f8:1C -> (f8, f8, f8)",
    ],
    "trim_rounds": [
        "f8:1C f8:1C f8 f8 f8 i8 f8 -> f8",
    ],
    "weighted_sums": [
        "f8:1C f8:1C f8:1C f8:1C f8:1C f8:1C",
    ],
}
