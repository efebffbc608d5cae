"""Pure decoders of real instruments' raw records (no files here: ``pipeline.io`` reads them).

- :mod:`stages.instruments.ptu`: PicoQuant T2/T3 records of every record type.
- :mod:`stages.instruments.linospad2`: LinoSPAD2 raw TDC words (firmware 2212b/2212s).
"""
