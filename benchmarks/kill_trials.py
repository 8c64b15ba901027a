"""Kill trials of issue 15: `kill -9` of `avatarctl fit` at >= 20 random moments (half of them inside checkpoint
writes) and of `ingest`, `render`, `eval` (3 each), each followed by the recovery check (see tests/test_crash.py).

    OMP_NUM_THREADS=1 python -m benchmarks.kill_trials [pytest args]     (~6 min on 2 shared cores)

Runs the soak tests of tests/test_crash.py (skipped in the normal suite) and prints their summaries.
"""

from __future__ import annotations

import os
import sys


def main(argv: list[str] | None = None) -> int:
    import pytest

    os.environ["AVATARCTL_SOAK"] = "1"
    args = ["tests/test_crash.py", "-s", "-q", "-p", "no:cacheprovider", "-k", "twenty or leave_nothing"]
    return pytest.main(args + list(sys.argv[1:] if argv is None else argv))


if __name__ == "__main__":
    sys.exit(main())
