"""The daemon's topology: the TOML file (its keys are in ``pipeline.stream.daemon``'s
docstring), validated into a :class:`Topology`, and the TDC ranges of its workers."""

from __future__ import annotations

import datetime as dt
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from schemas.errors import TcspcError

SOURCE_KINDS = ("sim", "capture", "udp", "file")
GRACE_S = 3.0  # after its upstream finished, a stage gets this long to stop by itself
STARTUP_S = 60.0  # ... counted from its first heartbeat (a loaded machine's start-up)


class TopologyError(TcspcError, ValueError):
    """A topology file that cannot run (names the file, the key and the problem)."""


@dataclass
class Topology:
    path: str
    state: Path
    run: str
    restarts: int
    metrics: str
    hwm: int
    source: dict
    histogram: dict
    range: dict | None
    sink: dict
    n_tdc: int
    journal_keep_gb: float | None = None
    journal_compression: str = "zstd"
    restart_window_s: float = 600.0
    restart_backoff_s: float = 0.5
    restart_backoff_max_s: float = 30.0
    curve: str | bool = "auto"
    view: dict | None = None   #: [view]: the web page beside the graph (None: no page)

    def endpoints(self) -> list[str]:
        """Every endpoint of the graph (for the CURVE decision)."""
        eps = [self.metrics, self.endpoint(self.sink, "sink")]
        eps += [self.endpoint(self.histogram, f"histogram-{i}", i)
                for i in range(self.workers)]
        if self.range:
            eps.append(self.endpoint(self.range, "range"))
        return eps

    @property
    def curve_on(self) -> bool:
        from pipeline.stream.curve import needs_curve

        return self.curve is True or (self.curve == "auto" and needs_curve(self.endpoints()))
    date: str = field(default_factory=lambda: dt.date.today().isoformat())

    @property
    def workers(self) -> int:
        return int(self.histogram.get("workers", 1))

    def endpoint(self, section: dict, name: str, i: int | None = None) -> str:
        if i is not None and "endpoints" in section:
            return section["endpoints"][i]
        if "endpoint" in section and i is None:
            return section["endpoint"]
        return f"ipc://{self.state.resolve()}/sock/{name}"


_KNOWN = {
    "daemon": {"state", "run", "restarts", "metrics", "hwm", "journal_keep_gb",
               "journal_compression", "restart_window_s", "restart_backoff_s",
               "restart_backoff_max_s", "curve"},
    "source": {"kind", "scene", "cycles", "seed", "chip_seed", "rate", "capture", "bind",
               "idle", "n_tdc", "repeat", "reorder_window", "max_jump_cycles", "file",
               "format", "firmware"},
    "histogram": {"workers", "measurement_cycles", "calibration", "n_tdc", "endpoints"},
    "range": {"calibration", "estimator", "endpoint"},
    "sink": {"out", "endpoint"},
    "view": {"port", "bind", "layout"},
}


def load_topology(path: str | Path | None, run: str | None = None,
                  overrides: dict | None = None) -> Topology:
    """Read and check a topology file (None: the embedded default, the street scene)."""
    where = str(path) if path else "<default topology>"
    if path:
        try:
            raw = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise TopologyError(f"{path}: topology file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise TopologyError(f"{path}: not valid TOML: {exc}") from None
    else:
        raw = default_topology()
    for key, sub in (overrides or {}).items():
        raw.setdefault(key, {}).update(sub)
    unknown = sorted(set(raw) - set(_KNOWN))
    if unknown:
        raise TopologyError(f"{where}: unknown sections {unknown}; known: {sorted(_KNOWN)}")
    for sec, keys in _KNOWN.items():
        extra = sorted(set(raw.get(sec, {})) - keys)
        if extra:
            raise TopologyError(f"{where} [{sec}]: unknown keys {extra}; known: {sorted(keys)}")
    d, src = raw.get("daemon", {}), raw.get("source")
    if not src:
        raise TopologyError(f"{where}: a [source] section is needed")
    kind = src.get("kind")
    if kind not in SOURCE_KINDS:
        raise TopologyError(f"{where} [source] kind {kind!r}: use one of {SOURCE_KINDS}")
    need = {"sim": "scene", "capture": "capture", "udp": "bind", "file": "file"}[kind]
    if need not in src:
        raise TopologyError(f"{where} [source]: kind {kind!r} needs {need!r}")
    hist = dict(raw.get("histogram", {}))
    if kind == "file":
        _check_file_source(src, hist, raw.get("range"), where)
    n_tdc = _source_n_tdc(src, hist, where)
    workers = int(hist.get("workers", 1))
    if not 1 <= workers <= n_tdc:
        raise TopologyError(f"{where} [histogram] workers = {workers}: use 1..{n_tdc}")
    if "endpoints" in hist and len(hist["endpoints"]) != workers:
        raise TopologyError(f"{where} [histogram]: {len(hist['endpoints'])} endpoints for "
                            f"{workers} workers")
    rng = raw.get("range")
    if rng is not None and "calibration" not in rng:
        raise TopologyError(f"{where} [range]: needs a calibration directory")
    for sec in (hist, rng or {}):
        cal = sec.get("calibration")
        if cal and not (Path(cal) / "tdc.parquet").exists():
            raise TopologyError(f"{where}: calibration {cal!r} is not a calibration directory "
                                "(run `tcspc flow run calibration_campaign` first)")
    state = Path(d.get("state", "data/daemon"))
    run = run or d.get("run") or (
        f"{Path(src.get('scene') or src.get('capture') or src.get('file') or 'udp').stem}-"
        f"{dt.datetime.now(dt.UTC).strftime('%Y%m%dT%H%M%SZ')}")
    metrics = d.get("metrics") or f"ipc://{state.resolve()}/sock/metrics"
    for ep in [metrics, *(hist.get("endpoints") or [])]:
        _check_endpoint(ep, where)
    from pipeline.stream.wire import ID_PATTERN

    if not ID_PATTERN.fullmatch(run):
        raise TopologyError(f"{where}: run id {run!r}: use 1..64 of [A-Za-z0-9._-] (it "
                            "becomes a directory name)")
    budget = {k: float(d.get(k, default)) for k, default in (
        ("restart_window_s", 600.0), ("restart_backoff_s", 0.5),
        ("restart_backoff_max_s", 30.0))}
    if any(v < 0 for v in budget.values()) or int(d.get("restarts", 10)) < 0:
        raise TopologyError(f"{where} [daemon]: restarts and restart times must be >= 0")
    return Topology(where, state, run, int(d.get("restarts", 10)), metrics,
                    int(d.get("hwm", 4)), src, hist, rng,
                    raw.get("sink", {"out": "data/stream"}), n_tdc,
                    float(d["journal_keep_gb"]) if "journal_keep_gb" in d else None,
                    _journal_compression(d.get("journal_compression", "zstd"), where),
                    **budget, curve=_curve(d.get("curve", "auto"), where),
                    view=_view(raw.get("view"), where))


def _view(sec: dict | None, where: str) -> dict | None:
    """The [view] section: ``port`` (0..65535, 0 any free one), ``bind`` (an address; a
    non-loopback one puts a token in the page's URL), ``layout`` ("16x8")."""
    if sec is None:
        return None
    port = sec.get("port", 5006)
    if not isinstance(port, int) or isinstance(port, bool) or not 0 <= port <= 65535:
        raise TopologyError(f"{where} [view] port = {port!r}: use 0..65535")
    bind = sec.get("bind", "127.0.0.1")
    if not isinstance(bind, str) or not bind:
        raise TopologyError(f"{where} [view] bind = {bind!r}: use an address, e.g. 127.0.0.1")
    layout = sec.get("layout")
    if layout is not None and not (isinstance(layout, str)
                                   and re.fullmatch(r"\d+x\d+", layout)):
        raise TopologyError(f"{where} [view] layout = {layout!r}: use COLUMNSxROWS, e.g. "
                            "\"16x8\"")
    return {"port": port, "bind": bind, **({"layout": layout} if layout else {})}


def _curve(value, where: str) -> str | bool:
    if value not in ("auto", True, False):
        raise TopologyError(f"{where}: [daemon] curve must be \"auto\", true or false, "
                            f"found {value!r}")
    return value


def _journal_compression(name, where: str) -> str:
    if name not in ("zstd", "none"):
        raise TopologyError(f"{where}: [daemon] journal_compression must be \"zstd\" or "
                            f"\"none\", found {name!r}")
    return name


def _check_endpoint(ep: str, where: str) -> None:
    if not ep.startswith(("ipc://", "tcp://", "inproc://")):
        raise TopologyError(f"{where}: endpoint {ep!r}: use ipc://PATH or tcp://HOST:PORT")


def _check_file_source(src: dict, hist: dict, rng, where: str) -> None:
    """An instrument's file (PTU T3, LinoSPAD2) replayed: its records are one ordered
    stream (a PTU record's time depends on the overflows before it), so one histogram
    worker, one measurement (the file), and no [range] (the range stage is the thesis
    chip's; `tcspc range` takes a T3 file's histograms offline)."""
    from pipeline.io.formats import FormatError, resolve_format

    path = Path(src["file"])
    if not path.is_file():
        raise TopologyError(f"{where} [source]: file {str(path)!r} not found")
    try:
        fmt = resolve_format(path, src.get("format"))
    except FormatError as exc:
        raise TopologyError(f"{where} [source]: {exc}") from None
    if fmt not in ("ptu", "linospad2"):
        raise TopologyError(f"{where} [source]: kind \"file\" replays a PTU or LinoSPAD2 "
                            f"file; {str(path)!r} is {fmt} (use kind = \"capture\")")
    src["format"] = fmt
    if fmt == "ptu":
        from pipeline.io.ptu import PtuError, read_header

        try:
            mode = read_header(path).format.mode
        except PtuError as exc:
            raise TopologyError(f"{where} [source]: {exc}") from None
        if mode != "T3":
            raise TopologyError(f"{where} [source]: {str(path)!r} holds {mode} records; the "
                                "stream histograms T3 files (`tcspc decode` takes T2)")
    if src.get("firmware", "2212b") not in ("2212b", "2212s"):
        raise TopologyError(f"{where} [source] firmware {src['firmware']!r}: use 2212b or "
                            "2212s")
    if int(hist.get("workers", 1)) != 1 or "measurement_cycles" in hist \
            or "calibration" in hist:
        raise TopologyError(f"{where} [histogram]: a file source takes one worker, no "
                            "measurement_cycles and no calibration (one measurement: the "
                            "file)")
    if rng is not None:
        raise TopologyError(f"{where}: no [range] with a file source (the range stage is the "
                            "thesis chip's; range a T3 file's histograms with `tcspc range`)")


def _source_n_tdc(src: dict, hist: dict, where: str) -> int:
    if src["kind"] == "file":
        return 1  # one ordered stream of records
    if src["kind"] == "sim":
        from stages.models.scene import load_scene

        return load_scene(src["scene"]).sensor.n_pixels
    if src["kind"] == "capture":
        from pipeline.io.capture import Capture

        return Capture(src["capture"]).meta.n_tdc
    n = src.get("n_tdc") or hist.get("n_tdc")
    if not n:
        raise TopologyError(f"{where}: a udp source needs n_tdc (in [source] or [histogram])")
    return int(n)


def default_topology() -> dict:
    root = Path(__file__).resolve().parents[2]
    return {"daemon": {"state": "data/daemon"},
            "source": {"kind": "sim", "scene": str(root / "scenes" / "street.toml"),
                       "cycles": 100_000, "seed": 1},
            "histogram": {"workers": 2, "measurement_cycles": 20_000},
            "sink": {"out": "data/stream"}}


def tdc_ranges(topo: Topology) -> list[tuple[int, int]]:
    from pipeline.stream.fanout import equal_ranges

    return equal_ranges(topo.n_tdc, topo.workers)
