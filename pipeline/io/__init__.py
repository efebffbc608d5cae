"""The project's own files: raw captures (``capture``: NAME.bin + NAME.json, zstd frames),
calibration directories (``caldir``: tdc.parquet, inl.parquet, meta.json) and atomic
writes (``atomic``). Imports ``stages`` and ``schemas`` only, no other room of
``pipeline``."""
