"""From measurement back to model.

Rooms: :mod:`metrology.formats` (profilometer file readers and writers),
:mod:`metrology.matching` (levelling, registration, comparison with the design, PSF from
measured heights), :mod:`metrology.calibration` (dual-pixel views and measured PSF
stacks), :mod:`metrology.diagnosis` (naming the effect the model misses),
:mod:`metrology.pipeline` (the demo's main job) and :mod:`metrology.cli` (the ``doe``
subcommands of this package).
"""

__all__: list[str] = []
