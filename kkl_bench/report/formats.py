"""The text formats of the leaderboard (``kkl-bench leaderboard --format``), named apart
from their rendering (:mod:`~kkl_bench.report.text`) so that the command line offers them
without loading pandas."""

FORMATS = ("markdown", "latex", "csv")
