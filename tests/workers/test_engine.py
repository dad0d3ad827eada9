"""The engine changes nothing in the process when imported; init_engine() does, once."""

from __future__ import annotations

import json
import subprocess
import sys

_SCRIPT = """
import json
from torch._inductor.codecache import CppPythonBindingsCodeCache as Cache
before = Cache.call_entry_function
import workers, workers.walk.walk, workers.run.shard, workers.walk.connections, workers.walk.harvest, workers.walk.kernels
after_import = Cache.call_entry_function
from workers.walk.engine import init_engine
init_engine(); init_engine()
print(json.dumps([before, after_import, Cache.call_entry_function]))
"""


def test_import_has_no_side_effects_and_init_engine_applies_once():
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=300, check=True)
    before, after_import, after_init = json.loads(out.stdout.strip().splitlines()[-1])
    assert after_import == before == "kernel({}); Py_RETURN_NONE;"
    assert after_init == "Py_BEGIN_ALLOW_THREADS kernel({}); Py_END_ALLOW_THREADS Py_RETURN_NONE;"
