"""Measurement to design: levelling on the unetched surface, registration of the
instrument frame to the design frame, the comparison (per-level heights, etch depths,
overlay, linewidth), the PSF predicted from measured heights and the 3-D rendering.
"""

__all__: list[str] = []
