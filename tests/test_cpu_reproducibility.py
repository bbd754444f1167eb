"""The method pins MKL's code path (``MKL_CBWR``) so that CPU results repeat bit for bit across
processes, which resume-after-kill relies on (``tests/test_resume.py``); a value the user set wins."""

from __future__ import annotations

import os
import subprocess
import sys

from tests.pipeline_helpers import ROOT

PROBE = "import os, morpheus_core; print(os.environ.get('MKL_CBWR'))"


def _probe(env: dict[str, str]) -> str:
    out = subprocess.run([sys.executable, "-c", PROBE], env={**env, "PYTHONPATH": str(ROOT)}, check=True,
                         capture_output=True, text=True, timeout=120)
    return out.stdout.strip()


def test_importing_the_method_pins_mkl_unless_the_user_chose() -> None:
    base = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    assert _probe(base) == "AUTO"
    assert _probe({**base, "MKL_CBWR": "COMPATIBLE"}) == "COMPATIBLE"
