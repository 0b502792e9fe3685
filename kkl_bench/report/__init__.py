"""The published board: one list of sections (:mod:`~kkl_bench.analysis.document`) rendered as
Markdown and as a page, and ``kkl-bench publish``, which writes them
(:mod:`~kkl_bench.report.publish`).

Layer: above the analysis (whose tables and document model it renders) and the run
layer's results store; only the CLI imports it."""
