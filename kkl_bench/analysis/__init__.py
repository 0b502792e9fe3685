"""How stored cells are analysed: summaries and leaderboards, paired comparisons and the
paper's findings, costs, scaling, training throughput, headroom, figures, and the document
model (:mod:`.document`) the tables are built in.

Layer: imports the run layer and everything under it; never the report or the CLI."""
