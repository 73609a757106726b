"""The results table: one row per cell, declared once and validated on every write, in one Parquet file that any
number of processes append to.

- graftcache.results.schema   what a row is: its columns, its format, the version of what its run_id hashes
- graftcache.results.upgrade  rows of older formats read as this format's, or refused saying how to rebuild them
- graftcache.results.reading  a results file as a table (strict, or conformed for a report)
- graftcache.results.writing  appends under the file's lease
- graftcache.results.claims   a cell's claim while it is computed; rows the file cannot take, kept and merged
- graftcache.results.same_result  when rows of one run_id are one result: the tolerance a merge checks them against

The table's names most callers use are here too.
"""

from graftcache.results.reading import done_run_ids, read, read_for_report
from graftcache.results.schema import (
    FORMAT_VERSION,
    IDENTITY_VERSION,
    REPORT_COLUMNS,
    SCHEMA,
    conform,
    empty,
    from_rows,
    make_run_id,
    validate,
)
from graftcache.results.writing import append

__all__ = ["FORMAT_VERSION", "IDENTITY_VERSION", "REPORT_COLUMNS", "SCHEMA", "append", "conform", "done_run_ids",
           "empty", "from_rows", "make_run_id", "read", "read_for_report", "validate"]
