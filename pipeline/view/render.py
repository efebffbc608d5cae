"""The page's text parts as HTML: the banner, the health table with its sparklines, the
accounting identity. Plain functions of plain data; every number the browser test reads
carries a ``data-field`` attribute."""

from __future__ import annotations

from html import escape

COLOURS = {"running": "#1a7f37", "finished": "#0969da", "failed": "#cf222e",
           "lost": "#cf222e", "absent": "#6e7781", "interrupted": "#bf8700",
           "incomplete": "#cf222e"}
HEALTH_COLOURS = {"ok": "#1a7f37", "finished": "#0969da", "silent": "#bf8700",
                  "unknown": "#6e7781",
                  "paused": "#bf8700", "restarting": "#bf8700", "down": "#cf222e"}
HEALTH_HELP = ("ok: a heartbeat in the last 5 s; silent: alive, no heartbeat; restarting: "
               "died, restart waiting out its backoff; down: process gone; paused: disk full; "
               "finished: done; unknown: the daemon stopped reporting")


def num(x, digits: int = 0) -> str:
    """A number for a person: thousands separated, '-' for none."""
    if x is None:
        return "-"
    if isinstance(x, float) and digits:
        return f"{x:,.{digits}f}"
    return f"{int(round(x)):,}"


def rate(x) -> str:
    """words/s or messages/s, in k or M."""
    if x is None:
        return "-"
    x = float(x)
    if abs(x) >= 1e6:
        return f"{x / 1e6:.2f} M"
    if abs(x) >= 1e3:
        return f"{x / 1e3:.1f} k"
    return f"{x:.1f}"


def sparkline(values, width: int = 110, height: int = 22, colour: str = "#0969da") -> str:
    """An inline SVG of the last values (empty box until there are two)."""
    vals = [float(v) for v in values if v is not None][-60:]
    box = (f'<svg width="{width}" height="{height}" style="vertical-align:middle;'
           f'background:#f6f8fa">')
    if len(vals) < 2:
        return box + "</svg>"
    top = max(max(vals), 1e-12)
    step = (width - 4) / (len(vals) - 1)
    pts = " ".join(f"{2 + i * step:.1f},{height - 2 - (height - 4) * max(v, 0) / top:.1f}"
                   for i, v in enumerate(vals))
    return (box + f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" '
            f'points="{pts}"/></svg>')


def banner(kind: str, text: str, extra: str = "") -> str:
    c = COLOURS.get(kind, "#6e7781")
    return (f'<div data-field="daemon-state" data-kind="{kind}" style="border-left:6px solid '
            f'{c};padding:6px 12px;background:#f6f8fa;font-size:15px;width:1180px">'
            f'<b style="color:{c}">{escape(kind.upper())}</b> {escape(text)}'
            f'{extra}</div>')


def health_table(rows: list[dict]) -> str:
    if not rows:
        return ('<p data-field="no-stages" style="color:#6e7781">No stage has reported: no '
                "daemon is running on this state directory.</p>")
    head = ("stage", "health", "pid", "restarts", "words/s", "", "messages/s", "",
            "queue", "blocked s", "rejected and quarantined, by reason", "not kept")
    out = ['<table data-field="health" style="border-collapse:collapse;font-size:13px">',
           "<tr>" + "".join(f'<th style="text-align:left;padding:2px 8px">{h}</th>'
                            for h in head) + "</tr>"]
    for r in rows:
        hc = HEALTH_COLOURS.get(r["health"], "#6e7781")
        rej = ", ".join(f"{escape(str(k))}: {v:,}" for k, v in sorted(r["rejected"].items()))
        cells = [
            ("stage", f"<b>{escape(r['stage'])}</b>"),
            ("health", f'<span style="color:{hc};font-weight:bold">{escape(r["health"])}'
                       "</span>" + (f" ({escape(str(r['reason']))})" if r.get("reason")
                                    else "")),
            ("pid", escape(str(r["pid"]))), ("restarts", num(r["restarts"])),
            ("words_s", rate(r["words_s"])), ("", sparkline(r["words_series"])),
            ("msgs_s", rate(r["msgs_s"])), ("", sparkline(r["msgs_series"], colour="#8250df")),
            ("queue", num(r["queue"])), ("blocked_s", num(r["blocked_s"], 1)),
            ("rejected", rej or "none"), ("quarantine_dropped", num(r["quarantine_dropped"]))]
        out.append(f'<tr data-stage="{escape(r["stage"])}" style="border-top:1px solid '
                   '#d0d7de">' + "".join(
                       f'<td data-field="{f}" style="padding:2px 8px">{v}</td>' if f else
                       f'<td style="padding:2px 0">{v}</td>' for f, v in cells) + "</tr>")
    out.append("</table>")
    out.append(f'<p style="color:#6e7781;font-size:12px;margin:4px 0">{HEALTH_HELP}. '
               "words/s: raw words through the source and the histogram workers (the range "
               "and sink stages pass messages: one per measurement and worker); queue: "
               "messages sent to a stage and not yet taken; blocked: time a stage waited on "
               "a slower one downstream.</p>")
    return "".join(out)


def datagrams(counts: dict) -> str:
    if not counts.get("datagrams"):
        return ""
    return (f'<p data-field="datagrams">UDP datagrams: {counts["datagrams"]:,} received, '
            f'<b data-field="lost_datagrams">{counts["lost_datagrams"]:,}</b> lost, '
            f'{counts["duplicates"]:,} duplicated, {counts["late"]:,} late.</p>')


def identity(ident: dict | None, run: str) -> str:
    """journaled = hit + no_hit + artifact + invalid_phase + malformed, holding or not."""
    if ident is None:
        return ""
    c = ident["classes"]
    terms = " + ".join(f'{k} <span data-field="n_{k}">{num(v)}</span>' for k, v in c.items())
    left = (f"<br>({ident['left']:,} measurements still being counted)"
            if ident.get("left") else "")
    if ident["final"]:
        ok = ident["holds"]
        colour, verdict = ("#1a7f37", "holds") if ok else ("#cf222e", "does NOT hold")
        withheld = (f" + withheld {num(ident['withheld'])} (damaged journal chunks)"
                    if ident["withheld"] else "")
        return (f'<div data-field="identity" data-holds="{str(ok).lower()}" '
                f'style="font-size:14px">Run {escape(run)} accounting: journaled '
                f'<span data-field="journaled">{num(ident["journaled"])}</span> = {terms}'
                f'{withheld} = {num(ident["classified"] + ident["withheld"])}: '
                f'<b style="color:{colour}">{verdict}</b>.</div>')
    bad = ident["rows_off"]
    verdict = (f'<b style="color:#cf222e">does NOT hold: {bad} TDC rows whose classes do not '
               "add up to their cycles</b>" if bad else
               '<b style="color:#1a7f37">holds so far</b> (every written measurement\'s '
               "classes add up to its words)")
    flight = ident["in_flight"]
    return (f'<div data-field="identity" data-holds="{"false" if bad else "running"}" '
            f'style="font-size:14px">Run {escape(run)} (running) accounting: journaled '
            f'<span data-field="journaled">{num(ident["journaled"])}</span>; in written '
            f'measurements {terms} = <span data-field="classified">'
            f'{num(ident["classified"])}</span>; <span data-field="in_flight">{num(flight)}'
            f"</span> in flight (journaled, in no written measurement yet): {verdict}. The "
            f"final balance is checked when the run ends.{left}</div>")


def note(text: str, kind: str = "info") -> str:
    if not text:
        return ""
    colour = {"info": "#6e7781", "warn": "#bf8700", "error": "#cf222e"}[kind]
    return f'<p data-field="note" style="color:{colour};margin:2px 0">{escape(text)}</p>'
