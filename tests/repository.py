"""The committed files that tests read: the board, its cells, the protocol and the README
of this checkout."""

from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]
"""The root of this checkout."""

BOARD = REPOSITORY / "leaderboard"
"""The committed board: its tables, figures and page."""

BOARD_CELLS = BOARD / "results" / "standard"
"""The committed board's cell records (profile ``standard``)."""

PROTOCOL = REPOSITORY / "docs" / "protocol.md"

README = REPOSITORY / "README.md"
