"""Prefect flows. Defaults set before Prefect is first imported (a user's environment wins):
the embedded server's first start on a fresh PREFECT_HOME runs its database migrations,
which takes longer than Prefect's 20 s default on a small machine (`make demo` on a fresh
clone timed out); and no telemetry from an offline tool."""

import os

os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
