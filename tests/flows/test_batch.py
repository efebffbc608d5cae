"""The ``batch`` flow: one task per file of a directory of chip captures and instrument
files, serially and on a local Dask cluster of two worker processes, with the same outputs."""

import json
import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest

DATA = Path(__file__).parents[1] / "data"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """Two simulated chip captures (the small scene, two chips), the HydraHarp T3 sample,
    the LinoSPAD2 sample, the PicoHarp T2 sample (no start-stop time: refused) and a file
    that is none of them (left out)."""
    from pipeline.offline.simulate import simulate_capture

    d = tmp_path_factory.mktemp("batch_in")
    root = Path(__file__).parents[2]
    for i in range(2):
        simulate_capture(root / "scenes" / "small16.toml", 4000, d / f"chip{i}", seed=i,
                         chip_seed=1 + i)
    shutil.copy(DATA / "picoquant" / "hydraharp_v20_t3.ptu", d)
    shutil.copy(DATA / "linospad2" / "test_data_2212b.dat", d)
    shutil.copy(DATA / "picoquant" / "LICENSE", d)
    return d


def outputs(run: Path) -> dict:
    """Every output table of a run by file name, without the metadata (paths, times)."""
    return {p.name: pq.read_table(p).replace_schema_metadata(None)
            for p in sorted((run / "histogram").glob("*.parquet"))}


def test_discover_finds_captures_and_instrument_files_by_content(inputs):
    from flows.batch import discover

    got = [(Path(p).name, f) for p, f in discover(inputs)]
    assert got == [("chip0", "tcspc"), ("chip1", "tcspc"), ("hydraharp_v20_t3.ptu", "ptu"),
                   ("test_data_2212b.dat", "linospad2")]


def test_a_dask_cluster_of_two_processes_gives_the_serial_runs_files(harness, inputs,
                                                                      tmp_path):
    """`tcspc flow run batch --dask ADDRESS`: one task per file on two worker processes;
    every histogram equals the serial run's, row for row."""
    from click.testing import CliRunner
    from distributed import LocalCluster

    from flows.batch import batch
    from pipeline.cli.app import cli

    serial = batch(str(inputs), out=str(tmp_path / "serial"))
    assert serial["files"] == 4 and serial["failed"] == 0
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        res = CliRunner().invoke(cli, ["flow", "run", "batch", "--dask-insecure", "--dask",
                                       cluster.scheduler_address, "-p", f"inputs={inputs}",
                                       "-p", f"out={tmp_path / 'dask'}"])
        assert res.exit_code == 0, res.output
        workers = {w["name"] for w in cluster.scheduler_info["workers"].values()}
    assert len(workers) == 2
    a = outputs(Path(serial["run"]))
    b = outputs(next((tmp_path / "dask" / "runs").iterdir()))
    assert sorted(a) == ["chip0.parquet", "chip1.parquet", "hydraharp_v20_t3.ptu.parquet",
                         "test_data_2212b.dat.parquet"]
    assert a.keys() == b.keys() and all(a[k].equals(b[k]) for k in a)
    counts = np.stack(a["chip0.parquet"].column("counts").to_numpy(zero_copy_only=False))
    assert counts.shape == (16, 512) and counts.sum() > 0
    files = pl.read_parquet(next((tmp_path / "dask" / "runs").iterdir()) / "files.parquet")
    assert files["error"].to_list() == [""] * 4
    params = json.loads((Path(serial["run"]) / "params.json").read_text())
    assert params["op"] == "histogram" and len(params["files"]) == 4


def test_a_file_that_fails_is_named_and_fails_the_run_after_the_others(harness, inputs,
                                                                         tmp_path):
    from flows.batch import batch

    d = tmp_path / "in"
    d.mkdir()
    shutil.copy(inputs / "test_data_2212b.dat", d)
    shutil.copy(DATA / "picoquant" / "picoharp_v30_t2.ptu", d)
    with pytest.raises(RuntimeError, match=r"1 of 2 files failed.*picoharp_v30_t2.ptu.*T2"):
        batch(str(d), out=str(tmp_path / "out"))
    run = next((tmp_path / "out" / "runs").iterdir())
    assert [p.name for p in (run / "histogram").iterdir()] == ["test_data_2212b.dat.parquet"]
    from prefect.exceptions import ParameterTypeError

    with pytest.raises(ParameterTypeError, match="op: Input should be 'histogram'"):
        batch(str(d), op="fold", out=str(tmp_path / "out"))  # refused by its type


def test_calibrate_and_range_a_directory(harness, inputs, caldir, tmp_path):
    """``op=calibrate``: a chip density capture's calibration directory, a LinoSPAD2 file's
    code density, a PTU file refused (its maker's calibration); ``op=range``: a chip
    capture with the calibration, the T3 file with its delay."""
    from flows.batch import batch
    from pipeline.io.caldir import load_calibration
    from pipeline.offline.simulate import simulate_capture
    from stages.models.scene import scene_from_dict

    d = tmp_path / "bench"
    d.mkdir()
    simulate_capture(scene_from_dict({"name": "dens", "sensor": {"n_pixels": 16},
                                      "ambient": [{"kind": "lux", "lux": 1200.0}]}),
                     40_000, d / "dens", seed=2)
    shutil.copy(inputs / "test_data_2212b.dat", d)
    shutil.copy(inputs / "hydraharp_v20_t3.ptu", d)
    with pytest.raises(RuntimeError, match=r"1 of 3 files failed.*hydraharp.*by its maker"):
        batch(str(d), op="calibrate", out=str(tmp_path / "cal"))
    run = next((tmp_path / "cal" / "runs").iterdir())
    assert load_calibration(run / "calibrate" / "dens").n_tdc == 16
    lino = pl.read_parquet(run / "calibrate" / "test_data_2212b.dat.code_density.parquet")
    assert lino.height == 64 and lino["hits"].sum() > 0

    r = tmp_path / "rng"
    r.mkdir()
    for name in ("chip0.bin", "chip0.json", "hydraharp_v20_t3.ptu"):
        shutil.copy(inputs / name, r)
    res = batch(str(r), op="range", out=str(tmp_path / "rng_out"), calibration=str(caldir),
                delay_ps=0.0)
    assert res["files"] == 2 and res["failed"] == 0
    chip = pl.read_parquet(Path(res["run"]) / "range" / "chip0.parquet")
    assert chip.height == 16 and chip["detected"].sum() >= 12
    assert chip.filter(pl.col("detected"))["distance_m"].median() == pytest.approx(1.5, abs=0.1)
    ptu = pl.read_parquet(Path(res["run"]) / "range" / "hydraharp_v20_t3.ptu.parquet")
    assert ptu.height == 2

    # a T3 file cut short is not ranged, as `tcspc range` refuses it: its row says why
    (r / "cut.ptu").write_bytes((inputs / "hydraharp_v20_t3.ptu").read_bytes()[:200_002])
    with pytest.raises(RuntimeError, match=r"1 of 3 files failed.*cut.ptu is truncated"):
        batch(str(r), op="range", out=str(tmp_path / "rng_cut"), calibration=str(caldir),
              delay_ps=0.0)
    run = next((tmp_path / "rng_cut" / "runs").iterdir())
    assert not (run / "range" / "cut.ptu.parquet").exists()
