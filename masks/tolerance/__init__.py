"""Tolerance analysis: Monte Carlo of the process model through the PSF engine, on Dask.

Modules: :mod:`.spec` (process distributions), :mod:`.metrics` (figures of merit per
sample), :mod:`.evaluate` (one sample: process -> surface -> PSF -> metrics),
:mod:`.runner` (batches on a dask.distributed cluster, resumable), :mod:`.sensitivity`
(one-at-a-time and Sobol indices through SALib), :mod:`.report` (report.json, plots,
report.md) and :mod:`.cli` (``doe tolerance``).
"""

__all__: list[str] = []
