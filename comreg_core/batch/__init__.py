"""Cohorts: many cases through one workflow (``comreg batch``, docs/batch.md).

The Snakefile shipped here (:data:`SNAKEFILE`) runs every case of a manifest
(:mod:`~comreg_core.batch.manifest`) through extract-ct -> [pretrain] -> extract-us -> register
-> report, each stage a ``comreg`` command run by :mod:`~comreg_core.batch.stage` (which records
its status), then writes the cohort summary (:mod:`~comreg_core.batch.summary`).
:func:`~comreg_core.batch.runner.run_batch` runs it through Snakemake's Python API; the
Snakefile also runs as it is with ``snakemake -s``. Only the runner imports Snakemake, and only
inside its functions.
"""

from pathlib import Path

#: The cohort workflow (package data).
SNAKEFILE = Path(__file__).resolve().with_name("Snakefile")
