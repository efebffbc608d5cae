"""The ``tcspc`` command line: the root group and the offline commands (``app``), the
calibration and model groups (``calibrate``, ``model``), and its generated reference
(``docs``). May import every room of ``pipeline``, but only inside the commands that use
them: ``tcspc --help`` imports none of numpy, pyarrow, numba, scipy, polars or prefect."""

from pipeline.cli.app import cli, main

__all__ = ["cli", "main"]
