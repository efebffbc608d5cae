"""Drivers over whole files: decode and histogram a capture (``datapath``), calibration
campaigns and the delay (``calibrate``), ranging a capture with a calibration
(``ranging``), simulated captures (``simulate``). They run the pure cores of ``stages``
in bounded memory. Imports ``pipeline.io``, ``stages`` and ``schemas``."""
