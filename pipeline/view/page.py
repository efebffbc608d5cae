"""One browser session's Bokeh document: the banner, then 1. health, 2. sensor and
3. calibration. The server pushes every change over the session's websocket (one
callback a second renders from the shared :class:`~pipeline.view.model.ViewModel`); the
browser polls nothing but a tiny ``/alive`` to notice that the server itself is gone."""

from __future__ import annotations

import hmac
import time

import numpy as np
from bokeh.layouts import column, row
from bokeh.models import (
    Checkbox,
    ColorBar,
    ColumnDataSource,
    Div,
    HoverTool,
    LinearColorMapper,
    Range1d,
    Select,
    Slider,
    Span,
    Spinner,
    TapTool,
)
from bokeh.palettes import Viridis256
from bokeh.plotting import figure
from jinja2 import Template

from pipeline.view import render
from pipeline.view.status import datagram_counts, health_rows

WIDTH = 1180
#: While following the newest, the sensor panel is redrawn at most this often.
SENSOR_EVERY_S = 2.0
NO_RUN = "(none)"
TEMPLATE = Template("""{% extends base %}
{% block title %}tcspc view{% endblock %}
{% block postamble %}<style>body{font-family:system-ui,sans-serif;margin:8px 16px}
#server-lost{display:none;position:fixed;top:0;left:0;right:0;padding:10px 16px;
background:#cf222e;color:white;font-size:16px;z-index:10}</style>{% endblock %}
{% block contents %}<div id="server-lost" data-field="server-lost"></div>{{ super() }}
<script>
(function () {
  var lost = false, box = document.getElementById("server-lost");
  function ping() {
    fetch("alive" + window.location.search, {cache: "no-store"}).then(function (r) {
      if (!r.ok) { throw new Error(r.status); }
      if (lost) { window.location.reload(); }
    }).catch(function () {
      lost = true;
      box.style.display = "block";
      box.textContent = "The view server is not answering: it was stopped, or it ended " +
        "with the daemon that started it ([view]). This page reloads by itself when it is " +
        "back; to look at a finished run, start `tcspc view`.";
    });
  }
  setInterval(ping, 3000);
})();
</script>{% endblock %}
""")


def _box(height: int) -> Div:
    """A Div of fixed size for text the server changes: a Div that may change size makes
    the browser lay the whole page out and redraw every plot (~25 % of a core while the
    page follows a run, against ~7 % with fixed sizes)."""
    return Div(width=WIDTH, height=height, styles={"overflow": "hidden"})


def health_height(rows: int) -> int:
    return 80 + 28 * rows


def _section(title: str, text: str) -> Div:
    return Div(text=f'<h2 style="margin:14px 0 2px 0">{title}</h2><p style="margin:0;'
                    f'color:#57606a">{text}</p>', width=WIDTH)


def _map(title: str, field: str, cmap_title: str, tooltips):
    src = ColumnDataSource({"x": [], "y": [], "tdc": [], field: [], "line": []})
    p = figure(title=title, width=560, height=330, tools="tap,reset", toolbar_location=None,
               x_range=Range1d(0, 16), y_range=Range1d(8, 0))
    mapper = LinearColorMapper(palette=Viridis256, nan_color="#d0d7de")
    p.rect("x", "y", 0.94, 0.94, source=src, fill_color={"field": field, "transform": mapper},
           line_color="line", line_width=2)
    p.text("x", "y", text="tdc", source=src, text_align="center", text_baseline="middle",
           text_font_size="8pt", text_color="#ffffff", text_alpha=0.8)
    p.add_tools(HoverTool(tooltips=tooltips))
    p.add_layout(ColorBar(color_mapper=mapper, title=cmap_title, width=10), "right")
    p.axis.visible = False
    p.grid.visible = False
    p.select_one(TapTool).mode = "replace"
    return p, src, mapper


class Page:
    """The widgets and sources of one session, and how they follow the model."""

    def __init__(self, doc, model):
        self.doc, self.m = doc, model
        self.shown: dict = {}
        model.wake()
        self.run = model.default_run()
        self.tdc: int | None = None
        self.banner = _box(58)
        self.run_pick = Select(title="Run (the daemon's, or any under the datasets)",
                               width=330)
        self.k_pick = Slider(title="Measurement", start=0, end=1, value=0, step=1, width=330)
        self.follow = Checkbox(label="follow the newest", active=True)
        self.tdc_pick = Spinner(title="TDC (or click a pixel)", low=0, step=1, value=0,
                                width=150)
        self.log = Checkbox(label="log scale", active=True)
        self.identity, self.health, self.datagrams = _box(66), _box(health_height(0)), \
            _box(0)
        self.sensor_info, self.hist_info, self.cal_info = _box(44), _box(26), _box(54)
        self._sensor_figures()
        self._calibration_figures()
        self.run_pick.on_change("value", self._on_run)
        self.k_pick.on_change("value_throttled", self._on_k)
        self.tdc_pick.on_change("value", lambda a, o, n: self._set_tdc(n))
        self.log.on_change("active", lambda a, o, n: self._draw_histogram(force=True))
        for src in (self.dist_src, self.count_src):
            src.selected.on_change("indices", lambda a, o, n, src=src: self._on_tap(src, n))
        # three roots, each laid out on its own: the text that changes every second (top)
        # never makes the browser lay out and redraw the plots below it
        doc.add_root(column(
            Div(text="<h1 style='margin:4px 0'>tcspc live view</h1><p style='margin:0;"
                     f"color:#57606a'>The daemon's health, what the sensor sees, and the "
                     f"calibration in use. State: {model.state}; datasets: {model.out}; "
                     "updates are pushed once a second.</p>", width=WIDTH),
            self.banner, row(self.run_pick, self.k_pick, self.follow, self.tdc_pick, self.log),
            _section("1. Health", "Every stage of the graph: is it alive, how fast, is data "
                                  "waiting or being refused; and does every word add up."),
            self.identity, self.health, self.datagrams, name="health"))
        doc.add_root(column(
            _section("2. Sensor", "The chosen measurement: distance and counts per pixel "
                                  "(hover for the numbers, click a pixel to see its "
                                  "histogram)."),
            self.sensor_info, row(self.dist_fig, self.count_fig), self.hist_info,
            self.hist_lin, self.hist_log, name="sensor"))
        doc.add_root(column(
            _section("3. Calibration", "The calibration the ranges use, and how far the LSB "
                                       "measured on this run's own background has drifted "
                                       "from it."),
            self.cal_info, row(self.lsb_fig, self.inl_fig), self.drift_fig, name="calibration"))
        self.update()
        doc.add_periodic_callback(self.update, 1000)

    # ------------------------------------------------------------------ figures
    def _sensor_figures(self):
        self.dist_fig, self.dist_src, self.dist_map = _map(
            "Distance per pixel (grey: nothing detected)", "distance_m", "m",
            [("TDC", "@tdc"), ("distance", "@distance_shown"), ("sigma", "@sigma_cm cm"),
             ("detected", "@detected"), ("signal", "@signal{0.0} counts")])
        self.count_fig, self.count_src, self.count_map = _map(
            "Hits per cycle per pixel (black edge: dead, red edge: hot)", "hits_per_cycle",
            "hits/cycle", [("TDC", "@tdc"), ("hits/cycle", "@hits_per_cycle{0.0000}"),
                           ("hits", "@n_hit"), ("flag", "@flag")])
        self.hist_src = ColumnDataSource({"code": [], "right": [], "count": [], "floor": []})
        figs = []
        for log in (False, True):
            p = figure(width=WIDTH, height=300, y_axis_type="log" if log else "linear",
                       x_axis_label="TDC code D1st (high codes: early photons)",
                       y_axis_label="counts", tools="xwheel_zoom,xpan,reset,hover",
                       x_range=Range1d(0, 512), toolbar_location="right")
            p.quad(left="code", right="right", top="count", bottom="floor", source=self.hist_src,
                   color="#57606a")
            p.select_one(HoverTool).tooltips = [("code", "@code"), ("count", "@count")]
            figs.append(p)
        self.hist_lin, self.hist_log = figs
        self.hist_lin.x_range = self.hist_log.x_range
        self.spans = {}
        for name, colour in (("reset", "#cf222e"), ("return", "#1a7f37")):
            spans = [Span(location=0, dimension="height", line_color=colour, line_width=2,
                          line_dash="dashed", visible=False) for _ in figs]
            for p, s in zip(figs, spans, strict=True):
                p.add_layout(s)
            self.spans[name] = spans

    def _calibration_figures(self):
        self.lsb_src = ColumnDataSource({"tdc": [], "lsb_ps": [], "lsb_at_light_ps": []})
        p = figure(title="LSB per TDC", width=580, height=280, x_axis_label="TDC",
                   y_axis_label="LSB (ps)", tools="hover,reset,box_zoom")
        p.scatter("tdc", "lsb_ps", source=self.lsb_src, color="#8c959f", size=5,
                  legend_label="at the density test's light")
        p.scatter("tdc", "lsb_at_light_ps", source=self.lsb_src, color="#0969da", size=5,
                  legend_label="at this measurement's light (eq. 5.1)")
        p.legend.label_text_font_size = "11px"
        p.legend.orientation = "horizontal"
        p.add_layout(p.legend[0], "below")
        self.lsb_fig = p
        self.inl_src = ColumnDataSource({"code": [], "inl": []})
        q = figure(title="INL of the chosen TDC", width=580, height=280,
                   x_axis_label="code", y_axis_label="INL (LSB)", tools="hover,reset")
        q.line("code", "inl", source=self.inl_src, color="#8250df")
        self.inl_fig = q
        self.drift_src = ColumnDataSource({"k": [], "median_ps": [], "p10_ps": [], "p90_ps": []})
        d = figure(title=DRIFT_TITLE, width=WIDTH, height=240,
                   x_axis_label="measurement", y_axis_label="drift (ps)", tools="hover,reset")
        d.varea("k", "p10_ps", "p90_ps", source=self.drift_src, color="#0969da", alpha=0.2)
        d.line("k", "median_ps", source=self.drift_src, color="#0969da", line_width=2)
        d.scatter("k", "median_ps", source=self.drift_src, color="#0969da", size=5)
        d.add_layout(Span(location=0, dimension="width", line_color="#57606a"))
        self.drift_fig = d

    # ------------------------------------------------------------------ callbacks
    def _on_run(self, attr, old, new):
        # (the value comes from the websocket: only a run found under the datasets or the
        # daemon's is taken, never a path: `../..` reached another run's files before)
        if new and new != self.run and new != NO_RUN and self.m.run_known(new):
            self.run, self.tdc = new, None
            self.follow.active = True
            self.shown["sensor_at"] = 0.0  # drawn now, not at the next 2 s
            self.update()

    def _on_k(self, attr, old, new):
        self.follow.active = False
        self.update()

    def _on_tap(self, src, indices):
        if indices:
            self._set_tdc(src.data["tdc"][indices[0]])

    def _set_tdc(self, tdc):
        if tdc is not None and int(tdc) != self.tdc:
            self.tdc = int(tdc)
            self.tdc_pick.value = self.tdc
            self._draw_histogram(force=True)
            self._draw_inl()

    def _put(self, widget, attr: str, value) -> None:
        """Set only what changed (every change is pushed to the browser)."""
        key = (id(widget), attr)
        if self.shown.get(key) != value:
            self.shown[key] = value
            setattr(widget, attr, value)

    # ------------------------------------------------------------------ the update
    def update(self):
        self.doc.hold("combine")  # every change of this update in one message
        try:
            self._update()
        finally:
            self.doc.unhold()

    def _update(self):
        m = self.m
        st = m.daemon()
        self._put(self.banner, "text", render.banner(st.kind, st.text))
        rows = health_rows(m.status, m.history, stale=st.kind == "lost")
        self._put(self.health, "height", health_height(len(rows)))  # (a new size: rarely)
        self._put(self.health, "text", render.health_table(rows))
        grams = render.datagrams(datagram_counts(m.status))
        self._put(self.datagrams, "height", 26 if grams else 0)
        self._put(self.datagrams, "text", grams)
        runs = [r["run"] for r in m.runs]
        if m.live_run and m.live_run not in runs:
            runs.insert(0, m.live_run)
        if self.run is None:
            self.run = m.default_run()
        if self.run and self.run not in runs:
            runs.insert(0, self.run)
        self._put(self.run_pick, "options", runs or [NO_RUN])
        self._put(self.run_pick, "value", self.run or NO_RUN)
        if not self.run:
            self._put(self.sensor_info, "text", render.note(
                f"No run under {m.out} yet, and no daemon status in {m.state}. Start one "
                "(tcspc daemon) or point --out / --state at a run's directories.", "warn"))
            return
        tr = m.track(self.run)
        have = tr.index.have["histograms"]
        ident = tr.identity
        self._put(self.identity, "text", render.identity(ident, self.run)
                  if have or ident["journaled"] or ident["final"] else "")
        if not have:
            known = m.run_known(self.run)
            self._put(self.sensor_info, "text", render.note(
                f"Run {self.run}: no measurement written yet under {m.out} (the first comes "
                "after one measurement's cycles)." if known else
                f"Run {self.run}: not found under {m.out} (runs there: "
                f"{', '.join(r['run'] for r in m.runs) or 'none'}).", "warn"))
            return
        self._put(self.k_pick, "end", max(len(have) - 1, 1))
        if self.follow.active:
            self._put(self.k_pick, "value", len(have) - 1)
        pos = min(int(self.k_pick.value), len(have) - 1)
        now = time.time()
        if not self.follow.active or now - self.shown.get("sensor_at", 0) >= SENSOR_EVERY_S:
            self.shown["sensor_at"] = now  # (a fast replay: the newest, every 2 s)
            self._show_measurement(tr, have[pos], len(have))
        self._draw_drift()

    def _show_measurement(self, tr, k: int, count: int):
        got = self.m.measurement(self.run, k)
        if got is None:
            return
        self.cur = got
        meas, r = got["meas"], got["ranges"]
        if self.tdc is None:
            self._set_tdc(self._interesting_tdc(got))
        key = (self.run, k, r is not None, self.m.calibration is not None)
        if self.shown.get("meas") == key:
            return
        self.shown["meas"] = key
        n = meas.tdc.size
        self.tdc_pick.high = n - 1
        layout = self.m.layout(n)
        x, y = meas.tdc % layout[0] + 0.5, meas.tdc // layout[0] + 0.5
        if self.m.geometry is not None:  # (issue 35: each TDC at its row and col)
            from pipeline.view.sensor import geometry_xy

            x, y, layout = geometry_xy(meas.tdc, self.m.geometry)
            x, y = x + 0.5, y + 0.5
        dead, hot = got["dead"], got["hot"]
        hpc = meas.classes["hit"] / np.maximum(meas.cycles, 1)
        for p in (self.dist_fig, self.count_fig):
            p.x_range.end, p.y_range.start = layout[0], layout[1]
        self.count_src.data = {
            "x": x, "y": y, "tdc": meas.tdc, "hits_per_cycle": hpc, "n_hit": meas.classes["hit"],
            "flag": np.where(dead, "dead", np.where(hot, "hot", "")),
            "line": np.where(dead, "black", np.where(hot, "#cf222e", "white"))}
        self.count_map.low, self.count_map.high = float(hpc.min()), float(max(hpc.max(), 1e-9))
        if r is not None:
            det = r["detected"].to_numpy()
            d = np.where(det, r["distance_m"].to_numpy(), np.nan)
            self.dist_src.data = {
                "x": x, "y": y, "tdc": meas.tdc, "distance_m": d,
                "distance_shown": [f"{v:.3f} m" if np.isfinite(v) else "none" for v in d],
                "sigma_cm": np.round(r["sigma_m"].to_numpy() * 100, 2), "detected": det,
                "signal": r["signal_counts"].to_numpy(), "line": np.full(n, "white")}
            if np.isfinite(d).any():
                self.dist_map.low, self.dist_map.high = float(np.nanmin(d)), float(np.nanmax(d))
        else:
            self.dist_src.data = {"x": [], "y": [], "tdc": [], "distance_m": [],
                                  "distance_shown": [], "sigma_cm": [], "detected": [],
                                  "signal": [], "line": []}
        flags = [f"dead: {', '.join(map(str, meas.tdc[dead]))}" if dead.any() else "no dead pixel",
                 f"hot: {', '.join(map(str, meas.tdc[hot]))}" if hot.any() else "no hot pixel"]
        det_n = int(r["detected"].sum()) if r is not None else 0
        self._put(self.sensor_info, "text", (
            f'<p data-field="measurement" style="margin:2px 0">Measurement <b>{meas.name}</b> '
            f"({count} written so far): {int(meas.cycles.max()):,} cycles, "
            f"{got['light']:.3f} detections per pixel per cycle; "
            f'<span data-field="detected">{det_n}</span> of {n} pixels detect a return; '
            f"{'; '.join(flags)}.</p>" + render.note(got["note"] if r is None else "")))
        self._draw_histogram(force=True)
        self._draw_lsb(got["light"])

    def _interesting_tdc(self, got) -> int:
        r = got["ranges"]
        if r is not None and r["detected"].any():
            return int(r.filter(r["detected"]).sort("signal_counts")["tdc"][-1])
        return int(got["meas"].tdc[np.argmax(got["meas"].classes["hit"])])

    def _draw_histogram(self, force=False):
        got = getattr(self, "cur", None)
        if got is None or self.tdc is None:
            return
        meas = got["meas"]
        hit = np.flatnonzero(meas.tdc == self.tdc)
        if hit.size == 0:
            return
        i = int(hit[0])
        counts = meas.counts[i].astype(np.float64)
        log = bool(self.log.active)
        self.hist_log.visible, self.hist_lin.visible = log, not log
        codes = np.arange(counts.size)
        self.hist_src.data = {"code": codes, "right": codes + 1,
                              "count": np.maximum(counts, 0.5) if log else counts,
                              "floor": np.full(counts.size, 0.5 if log else 0.0)}
        parts = [f"TDC <b data-field='tdc'>{self.tdc}</b>: {int(counts.sum()):,} hits in "
                 f"{int(meas.cycles[i]):,} cycles"]
        rc, ret = int(got["reset_code"][i]), float(got["return_code"][i])
        for span in self.spans["reset"]:
            span.location, span.visible = rc + 0.5, rc >= 0
        if rc >= 0:
            parts.append(f"<span style='color:#cf222e'>reset peak (the window's end) at code "
                         f"{rc}</span>")
        for span in self.spans["return"]:
            span.location, span.visible = ret, bool(np.isfinite(ret))
        r = got["ranges"]
        if np.isfinite(ret) and r is not None:
            row_ = r.filter(r["tdc"] == self.tdc)
            parts.append(f"<span style='color:#1a7f37'>detected return at code {ret:.1f}: "
                         f"<span data-field='distance'>{row_['distance_m'][0]:.3f}</span> m "
                         f"&plusmn; {row_['sigma_m'][0] * 100:.1f} cm</span>")
        elif r is not None:
            parts.append("no return detected" if not got["note"] else got["note"])
        self._put(self.hist_info, "text", "<p style='margin:2px 0'>" + "; ".join(parts)
                  + ".</p>")

    def _draw_lsb(self, light):
        cal = self.m.calibration
        if cal is None:
            self._put(self.cal_info, "text", render.note(
                f"No calibration to show: {self.m.cal_error}.", "warn"))
            return
        key = (id(cal), round(light, 3))  # the same light to 0.1 %: nothing to redraw
        if self.shown.get("lsb") == key:
            return
        self.shown["lsb"] = key
        from pipeline.view.sensor import calibration_frames

        f = calibration_frames(cal, light)
        at = f["lsb_at_light_ps"]
        self.lsb_src.data = {"tdc": f["tdc"], "lsb_ps": f["lsb_ps"],
                             "lsb_at_light_ps": at if at is not None else f["lsb_ps"] * np.nan}
        ok = np.isfinite(f["delay_ps"])
        self._put(self.cal_info, "text", (
            f"<p style='margin:2px 0'>Calibration <code data-field='calibration'>{f['path']}"
            f"</code>: {cal.n_tdc} TDCs ({int((~f['ok']).sum())} flagged); LSB "
            f"{np.nanmin(f['lsb_ps']):.2f}-{np.nanmax(f['lsb_ps']):.2f} ps at the density "
            f"test's light, <span data-field='lsb_now'>"
            f"{np.nanmedian(at) if at is not None else float('nan'):.2f}</span> ps (median) "
            f"at this measurement's; INL RMS median {np.nanmedian(f['inl_rms_lsb']):.2f} LSB; "
            f"delay on {int(ok.sum())} TDCs.</p>" + render.note(f["note"], "warn")))
        self._draw_inl()

    def _draw_inl(self):
        cal = self.m.calibration
        if cal is None or self.tdc is None or self.tdc >= cal.n_tdc:
            return
        if self.shown.get("inl") == (id(cal), self.tdc):
            return
        self.shown["inl"] = (id(cal), self.tdc)
        inl = np.asarray(cal.density.inl_lsb[self.tdc], np.float64)
        self.inl_src.data = {"code": np.arange(inl.size), "inl": inl}
        self.inl_fig.title.text = f"INL of TDC {self.tdc}"

    def _draw_drift(self):
        s = self.m.drift_series(self.run)
        key = (self.run, s["k"].size, len(s["flagged"]))
        if self.shown.get("drift") != key:
            self.shown["drift"] = key
            self.drift_src.data = {k: s[k] for k in ("k", "median_ps", "p10_ps", "p90_ps")}
            self.drift_fig.title.text = DRIFT_TITLE + drift_flag_note(s["flagged"])


DRIFT_TITLE = ("Online LSB estimate minus the calibration's, over the run (median over "
               "TDCs; band: 10-90 %)")


def drift_flag_note(flagged: dict[int, str]) -> str:
    """What the drift plot's title adds for the TDCs it leaves out (estimate untrusted)."""
    if not flagged:
        return ""
    tdcs = sorted(flagged)
    shown = ", ".join(map(str, tdcs[:8])) + (", ..." if len(tdcs) > 8 else "")
    return (f"; left out, estimate untrusted: TDC {shown} ({flagged[tdcs[0]]})")


#: the cookie a page's first load with its token sets (pipeline.view.server's auth)
COOKIE = "tcspc_view_token"


def make_document(model, token: str | None):
    """The Bokeh application's function: a page per session (the token checked first)."""

    def build(doc):
        doc.title = "tcspc view"
        doc.template = TEMPLATE
        if token is not None:  # (the server's auth provider checked it too)
            req = doc.session_context.request if doc.session_context else None
            got = ((req.arguments if req is not None else {}).get("token") or [b""])[0]
            got = got.decode() if isinstance(got, bytes) else str(got)
            # a reload without the query carries the cookie the token's first load set
            cookie = (getattr(req, "cookies", None) or {}).get(COOKIE, "")
            if not any(hmac.compare_digest(g.encode(), token.encode())
                       for g in (got, cookie) if g):
                doc.add_root(Div(text="<h1>Forbidden</h1><p>This page needs the token of its "
                                      "URL (printed by `tcspc view`, and in STATE/view.url)."
                                      "</p>"))
                return
        Page(doc, model)

    return build
