"""What a facet's result is, apart from the loop that produces it: the record and its one builder
(``record.py``), the verdict against the recipe's limits (``verdict.py``), the fault codes (``faults.py``),
the charted figures and their specification limits (``specs.py``), the optical figures
(``optical_figures.py``), what a shift's facets add up to (``shift.py``) and how a value with its
expanded uncertainty is written, wherever it is shown (``formatting.py``).

Below the station's loop: ``inspect``, the production loop, ``reprocess``, the reports, the line's page
and the configuration all read a result through this package, and it imports none of them.
"""
