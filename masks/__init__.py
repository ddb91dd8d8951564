"""Mask making: 16 levels to binary masks (``decompose``), merged Manhattan polygons
(``polygons``), the pixel grid and GDSII records (``grid``, ``gds_records``, ``gds_read``,
``verify``), the die and plate layouts (``gds``, ``layout``, ``plate``), the process model
(``process``, ``litho``, ``moments``, ``effects``) and tolerance analysis (``tolerance``)."""

__all__: list[str] = []
