"""The daemon's topology: the TOML file (its keys are in ``pipeline.stream.daemon``'s
docstring), validated into a :class:`Topology`, and the TDC ranges of its workers."""

from __future__ import annotations

import datetime as dt
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from pipeline.io.limits import FileTooLarge, capped, load_toml
from schemas.errors import TcspcError
from stages.codec import MAX_TDC

#: stages.ranging.ESTIMATORS, named here so that checking a topology does not import the
#: ranging kernels (numba, scipy: 0.5 s of the daemon's start); a test checks they agree
ESTIMATORS = ("fast", "centroid", "matched", "gaussfit", "ml")

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
    journal_compression: str = "zstd-nohit"
    restart_window_s: float = 600.0
    restart_backoff_s: float = 0.5
    restart_backoff_max_s: float = 30.0
    curve: str | bool = "auto"
    view: dict | None = None   #: [view]: the web page beside the graph (None: no page)
    heartbeat_deadline_s: float = 60.0  #: a live stage silent this long is frozen: SIGKILL
    restart_refill_s: float = 60.0  #: the restart budget earns one back per this long
    exporter: dict | None = None  #: [metrics]: Prometheus metrics over HTTP (None: off)
    log_format: str = "text"   #: [log] format: "text" or "json" (JSON lines)
    fork_server: bool = True  #: stages forked from a pre-started server (forkstart)

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


# ------------------------------------------------------------------ the file's schema
# One typed model per section (pydantic v2, strict: "20000" is not a count, true is not a
# number); each field declares its type, its range and what 0 or a negative would mean.
# Unknown keys are refused; every problem of the file is reported in one pass.


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


class DaemonSection(_Section):
    state: str = Field("data/daemon", min_length=1, description="the state directory (the "
                    "daemon's own: created 0700)")
    run: str | None = Field(None, description="run id: 1..64 of [A-Za-z0-9._-] (default: the "
                         "source's name and the UTC time)")
    restarts: int = Field(10, ge=0, description="the restart budget: deaths of one stage "
                       "restarted back to back, one earned back per restart_refill_s (0: the "
                       "first death fails the run)")
    metrics: str | None = Field(None, description="heartbeat endpoint (default "
                             "ipc://STATE/sock/metrics)")
    hwm: int = Field(4, ge=1, le=1_000_000, description="messages queued per socket, >= 1 (0 "
                  "would mean unbounded in ZeroMQ: refused)")
    journal_keep_gb: float | None = Field(None, gt=0, description="journal kept, GB, > 0 "
                                       "(leave out: keep all)")
    journal_compression: Literal["zstd-nohit", "zstd", "none"] = Field(
        "zstd-nohit", description="journal segments as zstd frames of the words less their "
        "no-hit pattern, as zstd frames of the words, or raw")
    restart_refill_s: float | None = Field(None, gt=0, description="one restart earned back "
                                        "per this long, s, > 0 (default 60: 60 deaths an "
                                        "hour for ever; leave out with restart_window_s: "
                                        "restart_window_s / restarts)")
    restart_window_s: float | None = Field(None, gt=0, description="before issue 38 the "
                                        "budget's window, s: now it sets restart_refill_s "
                                        "= restart_window_s / restarts")
    restart_backoff_s: float = Field(0.5, ge=0, description="wait before a restart, s (0: "
                                  "at once)")
    restart_backoff_max_s: float = Field(30.0, ge=0, description="the longest backoff, s")
    curve: Literal["auto"] | bool = Field("auto", description='"auto", true or false')
    heartbeat_deadline_s: float = Field(60.0, ge=2, description="a live stage that sends no "
                                     "heartbeat for this long is frozen: SIGKILLed and "
                                     "restarted, s, >= 2")
    fork_server: bool = Field(True, description="start the stages as forks of a server "
                              "that imported their modules once (milliseconds a stage); "
                              "false: one new interpreter per stage (~0.3 CPU-s each)")


class SourceSection(_Section):
    kind: Literal["sim", "capture", "udp", "file"] = Field(..., description="sim | capture | udp "
                                                        "| file")
    scene: str | None = Field(None, description="the scene TOML simulated")
    cycles: int | None = Field(None, ge=1, description="laser cycles simulated, >= 1")
    seed: int | None = Field(None, ge=0, description="seed of the photons, >= 0")
    chip_seed: int | None = Field(None, ge=0, description="seed of the chip's LSB, INL and "
                                  "second stage, >= 0")
    rate: float | None = Field(None, gt=0, description="words (records) per s, > 0 (leave "
                            "out: as fast as the graph takes them)")
    capture: str | None = Field(None, description="the capture replayed (NAME.bin)")
    repeat: int | None = Field(None, ge=1, description="times the capture is replayed, >= 1")
    bind: str | None = Field(None, description="HOST:PORT to listen on, port 1..65535")
    idle: float | None = Field(None, gt=0, description="seconds without a datagram that end "
                            "the run, > 0 (leave out: listen until stopped)")
    n_tdc: int | None = Field(None, ge=1, le=MAX_TDC, description=f"the chip's TDCs, "
                           f"1..{MAX_TDC}")
    reorder_window: int | None = Field(None, ge=1, description="datagrams held to undo "
                                    "reordering, >= 1")
    max_jump_cycles: int | None = Field(None, ge=1, description="the furthest a first cycle "
                                     "may jump past the newest, >= 1")
    gate_ps: int | None = Field(None, ge=1_000, le=10_000_000, description="the run's gate "
                                "in ps, 1e3..1e7 (leave out: from a quorum of datagrams)")
    first_seq: int | None = Field(None, ge=0, le=2**32 - 1, description="the run's first "
                                  "datagram sequence, 0..2^32-1 (leave out: from a quorum)")
    peers: list[str] | None = Field(None, description='udp: the senders whose datagrams '
                                    'are read, "HOST" or "HOST:PORT" (leave out: the run '
                                    'locks onto the sender of its reference)')
    file: str | None = Field(None, description="a PTU T3 or LinoSPAD2 file replayed")
    format: str | None = Field(None, description="the file's format (leave out: read from "
                               "its content)")
    firmware: Literal["2212b", "2212s"] | None = Field(None, description="LinoSPAD2 "
                                                       "firmware (its pixel mapping)")
    wire: Literal["sparse", "words"] | None = Field(None, description='sim, capture and udp: '
                                                    '"sparse" (default) or "words"')


#: the [source] keys each kind takes (besides kind)
SOURCE_KEYS = {"sim": ("scene", "cycles", "seed", "chip_seed", "rate", "wire"),
               "capture": ("capture", "rate", "repeat", "wire"),
               "udp": ("bind", "idle", "n_tdc", "reorder_window", "max_jump_cycles", "gate_ps",
                       "first_seq", "wire", "peers"),
               "file": ("file", "format", "firmware", "rate")}


class HistogramSection(_Section):
    workers: int = Field(1, ge=1, description="histogram workers, 1..n_tdc")
    measurement_cycles: int | None = Field(None, ge=1, description="cycles per measurement, "
                                        ">= 1 (leave out: one measurement, the whole run)")
    calibration: str | None = Field(None, description="a calibration directory: the "
                                    "artifact bounds (Nmin, Nmax) per TDC")
    artifacts: Literal["count-as-hits"] | None = Field(
        None, description='"count-as-hits": without a calibration, a sim or udp stream\'s '
        'artifact words are counted as hits (recorded in the accounting)')
    n_tdc: int | None = Field(None, ge=1, le=MAX_TDC, description=f"1..{MAX_TDC}")
    endpoints: list[str] | None = Field(None, description="the workers' endpoints, one a "
                                        "worker (leave out: ipc://STATE/sock/NAME)")


class RangeSection(_Section):
    calibration: str = Field(..., description="a calibration directory")
    estimator: str = Field("ml", description="ml, fast, matched, centroid or gaussfit "
                           "(docs/ranging.md)")
    max_returns: int = Field(3, ge=1, le=16, description="1..16 returns a pixel (0 is not "
                             "'none': leave the section out to range nothing)")
    endpoint: str | None = Field(None, description="its endpoint (leave out: ipc://STATE/sock/NAME)")
    # issue 35: each measurement ranged with its neighbours (docs/ranging.md "On the chip")
    spatial: bool = Field(False, description="true: each measurement ranged with its "
                          "neighbours as the geometry's image, the histogram workers' parts "
                          "gathered first (max_returns 1..4)")
    hold: int | None = Field(None, ge=1, le=256, description="with spatial: measurements "
                             "held while their workers' parts gather, 1..256 (past that the "
                             "oldest is ranged with the parts it has, flagged, and ranged "
                             "again from the journal at the run's end; leave out: 2 hwm + 1 "
                             "source batches' measurements + 2 hwm, 8..256)")
    geometry: str | None = Field(None, min_length=1, description="with spatial: the "
                                 "array's layout (leave out: [sink] geometry)")


class SinkSection(_Section):
    out: str = Field("data/stream", min_length=1, description="the datasets' directory")
    endpoint: str | None = Field(None, description="its endpoint (leave out: ipc://STATE/sock/NAME)")
    # issue 35: each ranges message also as a point cloud (docs/geometry.md)
    pointcloud: Literal["las", "ply", "pcd", "mcap"] | None = Field(
        None, description="las, ply, pcd or mcap: each measurement's ranges also as a point "
        "cloud under OUT/pointcloud (needs geometry)")
    geometry: str | None = Field(None, min_length=1, description="a shipped geometry "
                                 "(thesis128, tmf8820, linospad2), a .toml or a .parquet")


class MetricsSection(_Section):
    port: int = Field(..., ge=0, le=65535, description="serve Prometheus metrics on this "
                      "port, 0..65535 (0: any free port, in STATE/metrics.url; leave the "
                      "section out: no metrics)")
    host: str = Field("127.0.0.1", min_length=1, description="the address to listen on (a "
                      "bearer token from STATE/metrics.token on every address)")


class LogSection(_Section):
    format: Literal["text", "json"] = Field("text", description='"text" (a timestamp, a '
                                            'level, the line) or "json" (one object a line: '
                                            'ts, level, stage, msg)')


class ViewSection(_Section):
    port: int = Field(5006, ge=0, le=65535, description="0..65535 (0: any free port, in "
                   "STATE/view.url)")
    bind: str = Field("127.0.0.1", min_length=1, description="an address, e.g. 127.0.0.1")
    layout: str | None = Field(None, pattern=r"^\d+x\d+$", description='COLUMNSxROWS, e.g. '
                            '"16x8"')
    geometry: str | None = Field(None, min_length=1, description="the maps laid out as "
                                 "this geometry's array (docs/geometry.md)")


SECTIONS: dict[str, type[_Section]] = {
    "daemon": DaemonSection, "source": SourceSection, "histogram": HistogramSection,
    "range": RangeSection, "sink": SinkSection, "view": ViewSection,
    "metrics": MetricsSection, "log": LogSection}


def _problem(where: str, sec: str, err: dict, model: type[_Section]) -> str:
    """One line for one pydantic error: the file, the section, the key, what came and what
    the key takes."""
    loc = list(err["loc"])
    key = "".join(f"[{x}]" if isinstance(x, int) else ("." if i else "") + str(x)
                  for i, x in enumerate(loc)) or "(section)"
    if err["type"] == "extra_forbidden":
        return (f"{where} [{sec}] {key}: unknown keys are refused; known: "
                f"{sorted(model.model_fields)}")
    if err["type"] == "missing":
        return f"{where} [{sec}] {key}: missing (needed)"
    if err["type"] == "model_type":
        return f"{where} [{sec}]: a section (a table), found {err['input']!r:.60}"
    if err["type"] == "literal_error":
        return f"{where} [{sec}] {key} = {err['input']!r:.60}: use one of {err['ctx']['expected']}"
    info = model.model_fields.get(str(loc[0]))
    hint = f"; {info.description}" if info is not None and info.description else ""
    return f"{where} [{sec}] {key} = {err['input']!r:.60}: {err['msg']}{hint}"


def _sections(raw: dict, where: str, problems: list[str]) -> dict[str, _Section | None]:
    out: dict[str, _Section | None] = {}
    for sec in sorted(set(raw) - set(SECTIONS)):
        problems.append(f"{where} [{sec}]: unknown section; known: {sorted(SECTIONS)}")
    for sec, model in SECTIONS.items():
        if sec not in raw:
            out[sec] = None
            continue
        try:
            out[sec] = model.model_validate(raw[sec])
        except ValidationError as exc:
            problems.extend(_problem(where, sec, e, model) for e in exc.errors())
            out[sec] = None
    return out


def load_topology(path: str | Path | None, run: str | None = None,
                  overrides: dict | None = None, writable: bool = True) -> Topology:
    """Read and check a topology file (None: the embedded default, the street scene).

    Every problem is found in one pass and raised as one :class:`TopologyError`, a line
    per problem naming the file, the section and the key. ``writable``: also check that the
    state and sink directories can be written (a reader such as `tcspc view` only reads)."""
    where = str(path) if path else "<default topology>"
    if path:
        try:
            raw = load_toml(path, "topology file")
        except FileNotFoundError:
            raise TopologyError(f"{path}: topology file not found") from None
        except FileTooLarge as exc:
            raise TopologyError(str(exc)) from None
        except OSError as exc:
            raise TopologyError(f"{path}: cannot read: {exc.strerror}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise TopologyError(f"{path}: not valid TOML: {exc}") from None
    else:
        raw = default_topology()
    for key, sub in (overrides or {}).items():
        raw.setdefault(key, {}).update(sub)
    problems: list[str] = []
    secs = _sections(raw, where, problems)
    if "source" not in raw:
        problems.append(f"{where}: a [source] section is needed")
    d = secs["daemon"] or DaemonSection()
    src_m, hist_m, rng_m = secs["source"], secs["histogram"], secs["range"]
    src = src_m.model_dump(exclude_unset=True) if src_m else None
    hist = hist_m.model_dump(exclude_unset=True) if hist_m else {}
    rng = rng_m.model_dump(exclude_unset=True) if rng_m else None
    sink = (secs["sink"] or SinkSection()).model_dump(exclude_none=True)
    n_tdc = None
    if src is not None:
        n_tdc = _check_source(src, hist, raw.get("range"), where, problems)
    elif isinstance(raw.get("source"), dict) and raw["source"].get("kind") in SOURCE_KEYS:
        _check_source_keys(raw["source"], where, problems)  # the rest of [source]'s problems
    workers = hist.get("workers", 1)
    if n_tdc is not None and hist_m is not None and workers > n_tdc:
        problems.append(f"{where} [histogram] workers = {workers}: use 1..{n_tdc} (one TDC "
                        "range per worker)")
    if hist.get("endpoints") is not None and len(hist["endpoints"]) != workers:
        problems.append(f"{where} [histogram] endpoints: {len(hist['endpoints'])} endpoints "
                        f"for {workers} workers")
    if rng_m is not None:
        if rng.get("estimator", "ml") not in ESTIMATORS:
            problems.append(f"{where} [range] estimator = {rng['estimator']!r}: use one of "
                            f"{ESTIMATORS}")
        if rng.get("spatial") or rng.get("geometry"):
            _check_spatial(rng, sink, where, problems)
    if src is not None and (hist_m is not None or "histogram" not in raw):
        _check_artifacts(src["kind"], hist, where, problems)  # (else [histogram]'s problem)
    for sec, body in (("histogram", hist), ("range", rng or {})):
        cal = body.get("calibration")
        if cal and not (Path(cal) / "tdc.parquet").exists():
            problems.append(f"{where} [{sec}] calibration = {cal!r}: not a calibration "
                            "directory (run `tcspc flow run calibration_campaign` first)")
    if sink.get("pointcloud") or sink.get("geometry"):  # issue 35: a cloud per measurement
        _check_cloud(sink, where, problems)
    state = Path(d.state)
    if writable and (secs["daemon"] is not None or "daemon" not in raw):
        _check_writable(state, where, "[daemon] state", problems)
    if writable and (secs["sink"] is not None or "sink" not in raw):
        _check_writable(Path(sink["out"]), where, "[sink] out", problems)
    from pipeline.stream.wire import ID_PATTERN, run_id_from

    run = run or d.run
    if run is not None and not ID_PATTERN.fullmatch(run):
        problems.append(f"{where} [daemon] run = {run!r}: use 1..64 of [A-Za-z0-9._-], not "
                        f"'.' or '..' (it becomes a directory name), e.g. "
                        f"{run_id_from(run)!r}")
    if run is None:
        name = Path((src or {}).get("scene") or (src or {}).get("capture")
                    or (src or {}).get("file") or "udp").stem
        run = run_id_from(name, f"-{dt.datetime.now(dt.UTC).strftime('%Y%m%dT%H%M%SZ')}")
    metrics = d.metrics or f"ipc://{state.resolve()}/sock/metrics"
    for label, ep in (("[daemon] metrics", metrics),
                      *((f"[histogram] endpoints[{i}]", e)
                        for i, e in enumerate(hist.get("endpoints") or [])),
                      ("[range] endpoint", (rng or {}).get("endpoint")),
                      ("[sink] endpoint", sink.get("endpoint"))):
        if ep is not None:
            _check_endpoint(ep, where, label, problems)
    if problems:
        raise TopologyError(capped(problems))
    view, exporter, logsec = secs["view"], secs["metrics"], secs["log"]
    refill = d.restart_refill_s or (d.restart_window_s / max(d.restarts, 1)
                                    if d.restart_window_s else 60.0)
    return Topology(where, state, run, d.restarts, metrics, d.hwm, src, hist, rng, sink,
                    n_tdc, d.journal_keep_gb, d.journal_compression,
                    refill * max(d.restarts, 1), d.restart_backoff_s, d.restart_backoff_max_s,
                    curve=d.curve, heartbeat_deadline_s=d.heartbeat_deadline_s,
                    view=None if view is None else view.model_dump(exclude_none=True),
                    restart_refill_s=refill,
                    exporter=None if exporter is None else exporter.model_dump(),
                    log_format=(logsec or LogSection()).format,
                    fork_server=d.fork_server)


def _check_spatial(rng: dict, sink: dict, where: str, problems: list) -> None:
    """``[range] spatial``: a geometry (its own or the sink's), 1..4 returns (any number
    of histogram workers: the range stage gathers their parts of a measurement)."""
    if not rng.get("spatial"):
        problems.append(f"{where} [range] geometry is for spatial = true")
        return
    geometry = rng.get("geometry") or sink.get("geometry")
    if not geometry:
        problems.append(f"{where} [range] spatial = true needs a geometry: [range] geometry "
                        "or [sink] geometry (docs/geometry.md)")
    else:
        from pipeline.io.geometry import load_geometry

        try:
            g = load_geometry(geometry)
        except ValueError as exc:
            problems.append(f"{where} [range] geometry = {geometry!r}: {exc}")
        else:
            if g.rows * g.cols < 2:
                problems.append(f"{where} [range] spatial = true: geometry {geometry!r} "
                                "has one pixel, and a pixel is ranged by its neighbours")
    if rng.get("max_returns", 3) > 4:
        problems.append(f"{where} [range] spatial = true: max_returns = "
                        f"{rng['max_returns']}; use 1..4")


def _check_cloud(sink: dict, where: str, problems: list[str]) -> None:
    if not sink.get("pointcloud") or not sink.get("geometry"):
        problems.append(f"{where} [sink] pointcloud and geometry go together (give both)")
        return
    from pipeline.io.geometry import load_geometry

    try:
        load_geometry(sink["geometry"])
    except ValueError as exc:
        problems.append(f"{where} [sink] geometry = {sink['geometry']!r}: {exc}")


def _check_artifacts(kind: str, hist: dict, where: str, problems: list[str]) -> None:
    """Artifact words are never counted as hits unasked: a sim or udp stream has no words
    to estimate the bounds from before it starts, so it needs a calibration or the
    explicit ``[histogram] artifacts = "count-as-hits"`` (which a calibration overrides:
    its bounds remove the artifacts, and the accounting names it)."""
    counted = hist.get("artifacts") == "count-as-hits"
    if kind in ("sim", "udp") and not counted and not hist.get("calibration"):
        problems.append(f"{where} [histogram]: a {kind} source needs calibration = DIR (its "
                        "artifact bounds; without one the stream has no words to estimate "
                        'them from at start), or artifacts = "count-as-hits" to count its '
                        "artifact words as hits (recorded in the run's accounting)")


def _check_source(src: dict, hist: dict, rng, where: str, problems: list[str]) -> int | None:
    """The [source] keys that depend on its kind; the chip's TDC count (None when it cannot
    be known)."""
    kind = src["kind"]
    need = SOURCE_KEYS[kind][0]
    if not _check_source_keys(src, where, problems):
        return None
    if kind == "file":
        before = len(problems)
        try:
            _check_file_source(src, hist, rng, where)
        except TopologyError as exc:
            problems.append(str(exc))
        return 1 if len(problems) == before else None
    try:
        return _source_n_tdc(src, hist, where)
    except TopologyError as exc:
        problems.append(str(exc))
    except Exception as exc:  # noqa: BLE001 - a scene or capture that cannot be read
        problems.append(f"{where} [source] {need} = {src[need]!r}: {exc}")
    return None


def _check_source_keys(src: dict, where: str, problems: list[str]) -> bool:
    """The [source] keys its kind needs and takes; False when the key it needs is missing."""
    kind = src["kind"]
    need = SOURCE_KEYS[kind][0]
    for key in sorted(set(src) - {"kind", *SOURCE_KEYS[kind]} & set(SourceSection.model_fields)):
        problems.append(f"{where} [source] {key}: not a key of kind {kind!r} (it takes "
                        f"{', '.join(SOURCE_KEYS[kind])})")
    if need not in src:
        problems.append(f"{where} [source] {need}: missing; kind {kind!r} needs {need!r}")
        return False
    bind = src.get("bind") if kind == "udp" else None
    if isinstance(bind, str):
        host, _, port = bind.rpartition(":")
        if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            problems.append(f"{where} [source] bind = {bind!r}: use HOST:PORT, port "
                            "1..65535 (e.g. 127.0.0.1:9000)")
    if kind == "udp" and src.get("peers") is not None:
        from pipeline.stream.udp.senders import parse_peers

        try:
            if not parse_peers(src["peers"]):
                raise ValueError("peers = []: no sender would be read (leave the key out "
                                 "to lock onto the reference's sender)")
        except ValueError as exc:
            problems.append(f"{where} [source] {exc}")
    return True


def _check_writable(path: Path, where: str, label: str, problems: list[str]) -> None:
    """A directory the daemon will write: it, or its nearest existing ancestor, must be a
    directory this user can create files in (probed with a temporary directory, removed)."""
    import tempfile

    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    if not p.is_dir():
        problems.append(f"{where} {label} = {str(path)!r}: {str(p)!r} is not a directory")
        return
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".tcspc-probe-", dir=p))
    except OSError as exc:
        problems.append(f"{where} {label} = {str(path)!r}: cannot write in {str(p)!r} "
                        f"({exc.strerror or exc})")


def _check_endpoint(ep: str, where: str, label: str, problems: list[str]) -> None:
    if not ep.startswith(("ipc://", "tcp://", "inproc://")):
        problems.append(f"{where} {label} = {ep!r}: use ipc://PATH or tcp://HOST:PORT")
    elif ep.startswith("tcp://"):
        port = ep.rpartition(":")[2]
        if not port.isdigit() or not 1 <= int(port) <= 65535:
            problems.append(f"{where} {label} = {ep!r}: the port must be 1..65535")


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
            or "calibration" in hist or "artifacts" in hist:
        raise TopologyError(f"{where} [histogram]: a file source takes one worker, no "
                            "measurement_cycles, no calibration and no artifacts (one "
                            "measurement: the file)")
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
            # (no calibration to hand: the simulated artifacts are counted, and said so)
            "histogram": {"workers": 2, "measurement_cycles": 20_000,
                          "artifacts": "count-as-hits"},
            "sink": {"out": "data/stream"}}


def spatial_geometry(topo: Topology) -> str | None:
    """The geometry the range stage ranges with its neighbours by (``[range] spatial``:
    its ``geometry``, else the sink's), None without spatial ranging."""
    if not (topo.range or {}).get("spatial"):
        return None
    return topo.range.get("geometry") or topo.sink.get("geometry")


#: the most words a source sends in one batch (a replayed capture's,
#: pipeline.cli.stream.REPLAY_BATCH_WORDS): a worker folds its part of a batch at once and
#: sends every measurement in it together
SOURCE_BATCH_WORDS = 1 << 20
HOLD_MIN, HOLD_MAX = 8, 256


def range_hold(topo: Topology) -> int:
    """``[range] hold``, else enough for one worker to be as far ahead of another as the
    queues let it: the source blocks only once a worker's input queue (2 hwm batches) is
    full, so a worker may have folded 2 hwm + 1 source batches' measurements more than
    another, and the other's parts of them may still be in its output queue (2 hwm
    messages): 8..256 (docs/ranging.md "On the chip")."""
    if (topo.range or {}).get("hold") is not None:
        return int(topo.range["hold"])
    mc = topo.histogram.get("measurement_cycles")
    if not mc:  # one measurement: the run
        return HOLD_MIN
    batch_cycles = max(1, SOURCE_BATCH_WORDS // topo.n_tdc)
    lag = (2 * topo.hwm + 1) * -(-batch_cycles // mc) + 2 * topo.hwm
    return min(HOLD_MAX, max(HOLD_MIN, lag))


def tdc_ranges(topo: Topology) -> list[tuple[int, int]]:
    from pipeline.stream.fanout import equal_ranges

    return equal_ranges(topo.n_tdc, topo.workers)
