"""Small datasets and status records written the way the sink and the daemon write them."""

import os
from types import SimpleNamespace

import numpy as np
import pyarrow.parquet as pq
import pytest

from stages.histogram import HistogramState

N = 16
RUN = "r1"


def write_part(out, run, k, first, hits, classes=None, schema="histograms"):
    """One worker's file of measurement k, as the sink names it."""
    n = hits.shape[0]
    cc = classes if classes is not None else np.stack(
        [hits.sum(axis=1), np.full(n, 100), np.zeros(n), np.zeros(n), np.zeros(n)])
    state = HistogramState(hits.astype(np.uint64), np.asarray(cc, np.uint64),
                           int(np.sum(cc)), tdc_offset=first)
    d = out / schema / "date=2026-01-02" / f"run={run}"
    d.mkdir(parents=True, exist_ok=True)
    pq.write_table(state.to_table(f"{run}-m{k:06d}"), d / f"part-{k:06d}-t{first:03d}.parquet")


def hits_for(n, k=0, peak=200):
    h = np.ones((n, 512), np.int64)
    h[:, 400:] = 0
    h[:, 395] = 30           # the reset peak, where the light ends
    h[:, peak] = 50 + k      # a return
    return h


def status(now, state="running", **stages):
    return {"run": RUN, "updated": now, "started": now - 60, "state": state,
            "pid": os.getpid(), "stages": stages, "queue_depth": {"sink": 2}}



@pytest.fixture
def vd():
    """The helpers above, for the tests of this directory."""
    return SimpleNamespace(N=N, RUN=RUN, write_part=write_part, hits_for=hits_for,
                           status=status)
