"""Many recorded sessions at once, on Dask (one laptop or a lab's cluster): offline evaluation
(`evaluate`) or the sim-to-real diagnosis (`sim2real`) of each recording, or the benchmark
sweeps over seeds (`push`, `localize`: sweeps.py), as one row per item of DIR/results.csv, a
summary across them in DIR/summary.md (runner.py says how it runs)."""

from afm_core.batch.evaluate import evaluate_recording
from afm_core.batch.items import config_hash, expand_items, file_sha256, parse_seeds
from afm_core.batch.runner import (
    KINDS,
    SEED_KINDS,
    BatchResult,
    Progress,
    dask_client,
    run_batch,
)
from afm_core.batch.sim2real import diagnose_recording
from afm_core.batch.table import ResultsTable, read_rows

__all__ = [
    "KINDS",
    "SEED_KINDS",
    "BatchResult",
    "Progress",
    "ResultsTable",
    "config_hash",
    "dask_client",
    "diagnose_recording",
    "evaluate_recording",
    "expand_items",
    "file_sha256",
    "parse_seeds",
    "read_rows",
    "run_batch",
]
