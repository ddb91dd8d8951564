"""Closing the fab loop: diagnosed fields -> systematic effects -> corrected masks and a job sheet.

Modules: :mod:`.diagnoses` (reading ``doe diagnose`` reports, design fingerprints),
:mod:`.systematic` (fields combined: mean, standard error, spread, what is systematic),
:mod:`.jobsheet` (per-mask settings for the next run), :mod:`.merit` (the figure of merit of
the design, the measured and the corrected wafer), :mod:`.process_spec` (the measured process
as a ``doe tolerance`` spec), :mod:`.page` (report.md) and :mod:`.run` (:func:`~metrology.correction.run.correct`, what
``doe correct`` calls).
"""

from .run import correct

__all__ = ["correct"]
