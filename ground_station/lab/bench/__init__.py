"""Benchmarks behind `qnav bench`; `common` holds the table/JSON output."""
