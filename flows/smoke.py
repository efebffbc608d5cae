"""A trivial flow: CI runs it on Prefect's embedded API so a broken dependency shows at once.

(A fresh prefect once pulled a fastapi whose ``Body()`` rejected ``min_items``, breaking the
embedded server on the first flow; pyproject pins ``fastapi<0.155`` for that.)
"""

from __future__ import annotations

from prefect import flow, task


@task
def count_words(counts: dict[str, int]) -> int:
    return sum(counts.values())


@flow(name="smoke")
def smoke(counts: dict[str, int]) -> int:
    """Sum word-class counts: one task, one flow, one result."""
    return count_words(counts)
