"""``python -m pipeline.cli``: the ``tcspc`` command."""

from pipeline.cli.app import main

main()
