"""Fresh seeds for parametrised tests, the same in every pytest-xdist worker.

Tests draw a new seed per session (``fresh_seed()``) so each run tries new inputs, but the seeds name
the tests (``test_x[1648176599]``), and xdist refuses to run when its workers collect different
names. So the draws come from one session seed: ``MORPHEUS_TEST_SEED`` when set (to rerun a failure's
seeds), else a random one that the main process puts into the environment before the workers start
(``tests/conftest.py``); pytest's header prints it.
"""

from __future__ import annotations

import os
import random
import secrets

TEST_SEED_ENV = "MORPHEUS_TEST_SEED"
_draws = random.Random()


def seed_session() -> int:
    """Fix the session seed (from ``MORPHEUS_TEST_SEED``, set to a random one when unset) and restart the draws."""
    seed = int(os.environ.setdefault(TEST_SEED_ENV, str(secrets.randbits(32))))
    _draws.seed(seed)
    return seed


def fresh_seed() -> int:
    """The next seed of this session's sequence (every worker collects the modules in the same order)."""
    return _draws.randrange(2**31)
