"""The page's maps laid out as a geometry's array (`tcspc view --geometry`, issue 35)."""

from __future__ import annotations

import json
import time
import weakref

import numpy as np

from pipeline.io.geometry import load_geometry
from stages.geometry import grid


def test_the_maps_take_the_geometry_s_rows_and_cols(tmp_path, vd, monkeypatch):
    from bokeh.document import Document
    from bokeh.models import ColumnDataSource

    from pipeline.view.model import ViewModel
    from pipeline.view.page import make_document

    monkeypatch.setattr("pipeline.view.page.SENSOR_EVERY_S", 0.0)
    out = tmp_path / "out"
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "status.json").write_text(json.dumps(vd.status(time.time())))
    for first in (0, 8):
        vd.write_part(out, vd.RUN, 0, first, vd.hits_for(8))
    m = ViewModel(tmp_path / "state", out, None, feed=False)
    m.geometry = grid("g", 8, 2, 20.0, 20.0)                # 16 TDCs on 8 rows x 2 cols
    m.refresh()

    class Ctx:
        request = type("R", (), {"arguments": {}})()

    doc, ctx = Document(), Ctx()
    doc._session_context = weakref.ref(ctx)
    make_document(m, None)(doc)
    [cb.callback() for cb in doc.session_callbacks]
    srcs = [s for s in doc.select({"type": ColumnDataSource})
            if "hits_per_cycle" in s.data and len(s.data["x"])]
    assert srcs, "no counts map drawn"
    d = srcs[0].data
    tdc = np.asarray(d["tdc"])
    assert np.array_equal(np.asarray(d["x"]), tdc % 2 + 0.5)
    assert np.array_equal(np.asarray(d["y"]), tdc // 2 + 0.5)
    assert load_geometry("thesis128").cols == 128
