"""The geometry files shipped with tcspc-lidar (TOML; docs/geometry.md describes the keys):
``thesis128`` (the thesis's 128-SPAD line behind an assumed cylindrical lens),
``tmf8820`` (the ams TMF8820's 3 x 3 zones) and ``linospad2`` (one back-end's 256 pixels of
LinoSPAD2's 512 x 1 line behind an assumed lens). A package only so that a wheel carries
them, as ``scenes/`` is; `--geometry NAME` finds them by name."""
