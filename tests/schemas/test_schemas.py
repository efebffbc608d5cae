from pathlib import Path

import pyarrow as pa
import pytest

from schemas import (
    ALL_SPECS,
    HISTOGRAMS,
    RANGES,
    SchemaMismatch,
    SchemaVersionError,
    TcspcError,
    docs_markdown,
    validate,
)

DOCS = Path(__file__).parents[2] / "docs" / "schemas.md"


@pytest.mark.parametrize("spec", ALL_SPECS, ids=lambda s: s.name)
def test_every_field_has_unit_and_description(spec):
    for f in spec.schema:
        assert b"unit" in f.metadata and f.metadata[b"description"], f.name
    assert spec.schema.metadata[b"tcspc.version"] == spec.version.encode()


def test_design_columns_are_present():
    # docs/design.md "Outputs": the contract's columns, in order, with their types.
    assert HISTOGRAMS.names[:4] == ["measurement", "tdc", "cycles", "counts"]
    # histograms 2.0: counts a variable list (512 for the chip, other code counts for the
    # instruments of pipeline/io/ptu.py and linospad2.py); 1.x files are upgraded on read
    assert HISTOGRAMS.schema.field("counts").type == pa.list_(pa.uint64())
    # ranges 2.0: a row per return (return_index, 0 the strongest) and a flag; 3.0: tdc
    # uint32 (pixel numbers up to 2^32 - 1); 1.x and 2.x files are upgraded on read
    # (pipeline/io/ranges.py)
    assert RANGES.schema.field("tdc").type == pa.uint32()
    assert RANGES.names == ["measurement", "tdc", "distance_m", "sigma_m", "fwhm_m",
                            "signal_counts", "background_per_bin", "detected", "estimator",
                            "return_index", "flag"]


def test_validator_names_column_expected_and_found():
    bad = pa.table({"measurement": ["m"], "tdc": pa.array([1], pa.int32())})
    with pytest.raises(SchemaMismatch, match=r"'tdc' should be uint16, found int32"):
        validate(bad, HISTOGRAMS)
    missing = pa.table({"measurement": ["m"]})
    with pytest.raises(SchemaMismatch, match=r"column 'tdc' \(uint16\) is missing"):
        validate(missing, HISTOGRAMS)
    assert issubclass(SchemaMismatch, TcspcError) and issubclass(SchemaMismatch, ValueError)


def test_reader_refuses_unknown_major_version_naming_both():
    HISTOGRAMS.check_version("2.7")  # a newer minor only adds fields: readable
    with pytest.raises(SchemaVersionError, match=r"version 3.0 .* knows version 2.0"):
        HISTOGRAMS.check_version("3.0")
    with pytest.raises(SchemaMismatch, match="expected a 'histograms' dataset"):
        HISTOGRAMS.check_metadata({b"tcspc.schema": b"ranges", b"tcspc.version": b"1.0"})


def test_generated_docs_do_not_drift():
    """docs/schemas.md is written from schemas/ (`make docs`); this fails when it drifts."""
    assert DOCS.read_text() == docs_markdown(), "docs/schemas.md is stale: run `make docs`"
