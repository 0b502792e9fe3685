"""``python -m kkl_bench.cli``: the ``kkl-bench`` command."""

import sys

from kkl_bench.cli import main

sys.exit(main())
