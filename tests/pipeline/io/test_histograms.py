"""histograms files: 2.0 written, 1.x (fixed 512-code lists, no instrument) still read."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.io.histograms import read_histograms, write_histogram_table
from schemas import HISTOGRAMS, SchemaMismatch, SchemaVersionError
from schemas.core import SchemaSpec, field
from stages.histogram import HistogramState

# The 1.0 contract as it was shipped (docs/design.md "Outputs"), written here from the old
# docs/schemas.md rather than taken from the code under test.
V1 = SchemaSpec("histograms", "1.0", tuple(
    field(n, t, "", n) for n, t in [
        ("measurement", pa.string()), ("tdc", pa.uint16()), ("cycles", pa.uint64()),
        ("counts", pa.list_(pa.uint64(), 512)), ("n_hit", pa.uint64()),
        ("n_no_hit", pa.uint64()), ("n_artifact", pa.uint64()),
        ("n_invalid_phase", pa.uint64()), ("n_malformed", pa.uint64())]))


def _v1_table(rng, n=3):
    hits = rng.integers(0, 50, (n, 512)).astype(np.uint64)
    cols = {"measurement": ["old"] * n, "tdc": pa.array(np.arange(n, dtype=np.uint16)),
            "cycles": pa.array(hits.sum(1) + 7),
            "counts": pa.FixedSizeListArray.from_arrays(pa.array(hits.ravel()), 512),
            "n_hit": pa.array(hits.sum(1)), "n_no_hit": pa.array(np.full(n, 7, np.uint64))}
    for c in ("n_artifact", "n_invalid_phase", "n_malformed"):
        cols[c] = pa.array(np.zeros(n, np.uint64))
    return pa.Table.from_pydict(cols, schema=V1.schema), hits


def test_v1_file_reads_as_2(tmp_path):
    table, hits = _v1_table(np.random.default_rng(1))
    pq.write_table(table, tmp_path / "old.parquet")
    got = read_histograms(tmp_path / "old.parquet")
    assert got.schema.metadata[b"tcspc.version"] == HISTOGRAMS.version.encode()
    assert got.schema.metadata[b"tcspc.upgraded_from"] == b"1.0"
    assert got.column("instrument").to_pylist() == ["tcspc-chip"] * 3
    assert got.column("bin_width_ps").null_count == 3
    assert np.array_equal(np.stack(got.column("counts").to_numpy(zero_copy_only=False)), hits)
    state = HistogramState.from_table(got)  # the chip path takes upgraded rows
    assert np.array_equal(state.hits, hits)


def test_round_trip_and_dataset_directory(tmp_path):
    rng = np.random.default_rng(2)
    hits = rng.integers(0, 9, (4, 512)).astype(np.uint64)
    cc = np.zeros((5, 4), np.uint64)
    cc[0] = hits.sum(1)
    state = HistogramState(hits, cc, int(cc.sum()))
    write_histogram_table(state.to_table("a"), tmp_path / "d" / "a.parquet", {"by": "test"})
    old, _ = _v1_table(rng)
    pq.write_table(old, tmp_path / "d" / "b.parquet")  # a dataset mixing versions
    got = read_histograms(tmp_path / "d")
    assert got.num_rows == 7 and set(got.column("measurement").to_pylist()) == {"a", "old"}
    one = read_histograms(tmp_path / "d" / "a.parquet")
    assert one.schema.metadata[b"tcspc.by"] == b"test"
    assert np.array_equal(HistogramState.from_table(one).hits, hits)


def test_refusals(tmp_path):
    table, _ = _v1_table(np.random.default_rng(3))
    meta = dict(table.schema.metadata)
    pq.write_table(table.replace_schema_metadata({**meta, b"tcspc.version": b"3.0"}),
                   tmp_path / "new.parquet")
    with pytest.raises(SchemaVersionError, match="3.0 is not readable"):
        read_histograms(tmp_path / "new.parquet")
    pq.write_table(table.replace_schema_metadata({**meta, b"tcspc.schema": b"ranges"}),
                   tmp_path / "other.parquet")
    with pytest.raises(SchemaMismatch, match="found 'ranges'"):
        read_histograms(tmp_path / "other.parquet")
    with pytest.raises(FileNotFoundError):
        read_histograms(tmp_path / "empty_dir_missing")


def test_instrument_rows_are_not_chip_rows():
    state = HistogramState(np.ones((1, 512), np.uint64), np.ones((5, 1), np.uint64), 5)
    t = state.to_table("m")
    t = t.set_column(t.schema.get_field_index("instrument"), "instrument",
                     pa.array(["picoquant-t3"]))
    with pytest.raises(ValueError, match="picoquant-t3"):
        HistogramState.from_table(t)
