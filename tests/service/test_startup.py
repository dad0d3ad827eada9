"""Start-up cost of the commands that launch worker processes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_parent_of_local_workers_does_not_import_torch():
    """`bssrdf run` submits and starts its workers at once: neither its command-line parser (every
    subcommand's is built) nor the job store and dataset modules it uses may import torch, which
    takes seconds that would come before every worker's own start."""
    code = (
        "import sys, service.cli, service.runner, service.store, service.datasets\n"
        "service.cli.build_parser()\n"
        "print('torch' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
