"""The package graph runs one way, schema <- workers <- service <- bench, the wings of workers/ in
their order, and the fold, the exports, the models and the schema never import torch (pyproject's
import-linter contracts, which see every import, function-local ones included; the last also at
run time, in a fresh interpreter)."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_import_layers_contract_is_kept():
    exe = shutil.which("lint-imports") or str(Path(sys.executable).with_name("lint-imports"))
    out = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]
    assert "3 kept, 0 broken" in out.stdout


def test_merge_and_publish_run_without_torch():
    """What a merge round and an export load (the fold, the tables, the exports, the publish)
    leaves torch unimported: a process that only merges never pays for it."""
    code = (
        "import sys\n"
        "import service.datasets.publish, workers.fold.job, workers.fold.output, workers.fold.configs\n"
        "import workers.exports, workers.models.tabulated\n"
        "import service.cli; service.cli.build_parser()\n"
        "loaded = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.'))\n"
        "assert not loaded, loaded[:5]\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
