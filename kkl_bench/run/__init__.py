"""How a run executes and stores cells: what a run is asked (:mod:`.spec`), the harness
that fits and scores (:mod:`.harness`, :mod:`.scoring`), the results store
(:mod:`.results`), regeneration and its ledger, fit-time estimates and verification.

Layer: imports the estimators and every layer under them; never the analysis, the report
or the CLI."""
