"""Campaigns: many simulated runs scored against truth, on Dask distributed (``bttsim campaign``).

:mod:`.spec` reads and expands a study spec, :mod:`.run` is the per-run task (simulate,
process with every processor, score), :mod:`.driver` submits the runs to a Dask cluster and
gathers them, :mod:`.results` and :mod:`.report` write ``results.parquet`` and ``report.md``.
Dask and pyarrow come with the ``campaign`` extra; nothing here is imported by the runtime.
"""

from .driver import CampaignOutcome, connect, run_campaign
from .run import USER_COLUMNS, execute_run, user_tables
from .spec import CampaignSpec, RunSpec, SpecError, expand, load_spec, spec_from_dict

__all__ = ["CampaignOutcome", "CampaignSpec", "RunSpec", "SpecError", "USER_COLUMNS", "connect", "execute_run",
           "expand", "load_spec", "run_campaign", "spec_from_dict", "user_tables"]
