"""Reports for the process and quality engineer: every picture and document the station draws from its
archive or from a re-analysis has its home here (docs/reanalysis.md, docs/quality.md). They draw and
write; finding the records, recipes and measurements is the report command's part
(:mod:`sofast_station.reanalysis.quality_reports`, :mod:`sofast_station.reanalysis.sources`).

- ``maps.py``: slope-error maps in the style of the method paper's Figs. 8-10;
- ``trend.py``: trend plots of an archive period;
- ``control_charts.py``: individuals and moving-range charts, yield, summary workbook (``report spc``; the
  statistics are :mod:`sofast_station.qc.spc`);
- ``acceptance.py``: a contract's evaluation and its histograms (``report acceptance``);
- ``certificate.py``, ``diff.py``, ``flux.py``: one facet's certificate, two measurements compared, the flux map;
- ``summary.py``: a record in words (``inspect``'s summary, the maps' text, ``reprocess``'s head), each figure as
  every screen writes it.

The modules are imported only when used (the package imports nothing), so that the command line can put
BLAS on one thread before numpy loads.
"""
