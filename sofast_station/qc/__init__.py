"""Quality-control statistics, pure (numpy in, numpy out; no files, no globals, no plotting).

- ``spc.py``: individuals / moving-range and EWMA charts, Western Electric and Nelson run rules,
  process capability (Cp, Cpk), average run lengths.
- ``acceptance.py``: sample sizes of the heliostat field acceptance guideline for a finite population,
  confidence intervals of a mean, normal and Weibull fits.

Pictures and workbooks built from them live in :mod:`sofast_station.report`; the line's drift alarm in
:mod:`sofast_station.station.drift`.
"""
