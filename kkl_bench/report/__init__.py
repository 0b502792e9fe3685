"""The published board: one list of sections (:mod:`~kkl_bench.report.model`) rendered as
Markdown and as a page, and ``kkl-bench publish``, which writes them
(:mod:`~kkl_bench.report.publish`)."""
