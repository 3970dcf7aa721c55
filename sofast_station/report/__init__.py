"""Reports for the process and quality engineer: every picture and document the station draws from its
archive or from a re-analysis has its home here (docs/reanalysis.md).

- ``maps.py``: slope-error maps in the style of the method paper's Figs. 8-10
  (:func:`~sofast_station.report.maps.slope_error_maps`, :func:`~sofast_station.report.maps.write_slope_error_maps`).
- ``trend.py``: trend plots of an archive period (:func:`~sofast_station.report.trend.write_trend`).

The modules are imported only when used (the package imports nothing), so that the command line can put
BLAS on one thread before numpy loads.
"""
