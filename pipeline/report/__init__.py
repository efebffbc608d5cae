"""What people look at: chapter-2 and calibration figures (``figures``), Markdown reports
(``report``) and the demo's checks (``demo``). Imports ``pipeline.io``,
``pipeline.offline``, ``stages`` and ``schemas``."""
