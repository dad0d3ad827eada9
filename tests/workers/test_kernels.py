"""Compiled kernels kept on disk between processes (workers.walk.kernels)."""

from __future__ import annotations

import ast
import logging
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

import workers.walk
from workers.walk import kernels
from workers.walk.kernels import GRAPH_MODULES, artifact_key, compile_kernel


@dataclass(frozen=True)
class _Consts:
    scale: float


def _relative_imports(module: str) -> set[str]:
    tree = ast.parse((Path(workers.walk.__file__).parent / f"{module}.py").read_text())
    return {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module}


def test_graph_modules_cover_what_the_compiled_graphs_import():
    """The source digest must cover every module a compiled graph's code can come from: the
    package-internal import closure of the modules that define compiled kernels."""
    seen, todo = set(), ["walk", "connections", "harvest"]
    while todo:
        m = todo.pop()
        if m not in seen:
            seen.add(m)
            todo.extend(_relative_imports(m) - {"kernels"})  # kernels compiles, adds no graph code
    assert seen <= set(GRAPH_MODULES), sorted(seen - set(GRAPH_MODULES))


def test_artifact_key_tracks_what_shapes_the_code():
    x = torch.zeros(8)
    base = artifact_key("k", _Consts(1.0), ([x, x], 3))
    assert base == artifact_key("k", _Consts(1.0), ([torch.ones(8), x], 3)), "values of tensors are not part of it"
    changed = [
        artifact_key("other", _Consts(1.0), ([x, x], 3)),
        artifact_key("k", _Consts(2.0), ([x, x], 3)),
        artifact_key("k", _Consts(1.0), ([torch.zeros(16), x], 3)),
        artifact_key("k", _Consts(1.0), ([x.double(), x], 3)),
        artifact_key("k", _Consts(1.0), ([x, x], 4)),
    ]
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(threads + 1)
        changed.append(artifact_key("k", _Consts(1.0), ([x, x], 3)))
    finally:
        torch.set_num_threads(threads)
    with torch.no_grad():
        changed.append(artifact_key("k", _Consts(1.0), ([x, x], 3)))
    assert len({base, *changed}) == len(changed) + 1


def test_artifact_key_refuses_arguments_it_cannot_describe():
    with pytest.raises(TypeError, match="cannot key"):
        artifact_key("k", None, (object(),))


def _axpy(xs, a, consts=_Consts(1.5)):
    x, y = xs
    return (x * consts.scale + y * a).sum()


def test_kernel_is_saved_loaded_and_rebuilt(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", str(tmp_path))
    x, y = torch.arange(16.0), torch.full((16,), 2.0)
    expected = float((x * 1.5 + y * 3.0).sum())

    first = compile_kernel(_axpy, "axpy", _Consts(1.5))
    assert float(first([x, y], 3.0)) == expected
    saved = sorted(tmp_path.glob("axpy-*.pt2"))
    assert len(saved) == 1
    stamp = saved[0].stat().st_mtime_ns

    # A new kernel object (as in a new process) loads the artifact instead of compiling.
    loaded = compile_kernel(_axpy, "axpy", _Consts(1.5))
    assert float(loaded([x, y], 3.0)) == expected
    assert sorted(tmp_path.glob("axpy-*.pt2")) == saved
    assert saved[0].stat().st_mtime_ns == stamp, "loaded, not compiled and written again"

    # Other shapes: a second variant and artifact; the first still serves its own shapes.
    x2, y2 = torch.arange(32.0), torch.ones(32)
    assert float(loaded([x2, y2], 3.0)) == float((x2 * 1.5 + y2 * 3.0).sum())
    assert len(list(tmp_path.glob("axpy-*.pt2"))) == 2
    assert float(loaded([x, y], 3.0)) == expected

    # A damaged artifact is compiled again, with a warning, and replaced.
    saved[0].write_bytes(b"not an artifact")
    with caplog.at_level(logging.WARNING, logger=kernels.__name__):
        again = compile_kernel(_axpy, "axpy", _Consts(1.5))
        assert float(again([x, y], 3.0)) == expected
    assert "did not load" in caplog.text
    assert saved[0].read_bytes() != b"not an artifact"


@dataclass
class _Pair:
    """A structure of arrays, as workers.walk.walk.Lanes."""

    a: torch.Tensor
    b: torch.Tensor


def _accumulate(pair: _Pair, scale: float):
    pair.a.copy_(pair.a + pair.b * scale)
    return (pair.a.sum(),)


def test_a_dataclass_of_views_is_passed_whole_saved_and_loaded(tmp_path, monkeypatch):
    """Kernels take structures of arrays whole (chunks of workers.walk.walk.Lanes): the artifact of a
    kernel called with a dataclass of views loads in a new kernel object (as in a new process),
    and the in-place writes of both reach the viewed storage, each in its own chunk."""
    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", str(tmp_path))
    a, b = torch.zeros(32), torch.arange(32.0)
    chunks = [_Pair(a[i : i + 16], b[i : i + 16]) for i in (0, 16)]
    first = compile_kernel(_accumulate, "accumulate")
    assert float(first(chunks[0], 2.0)[0]) == float(b[:16].sum() * 2.0)
    saved = sorted(tmp_path.glob("accumulate-*.pt2"))
    assert len(saved) == 1
    stamp = saved[0].stat().st_mtime_ns

    loaded = compile_kernel(_accumulate, "accumulate")
    assert float(loaded(chunks[1], 2.0)[0]) == float(b[16:].sum() * 2.0)
    assert saved[0].stat().st_mtime_ns == stamp and sorted(tmp_path.glob("accumulate-*.pt2")) == saved, "loaded, not compiled"
    assert torch.equal(a, b * 2.0), "both chunks written in place, nothing else"


def test_calls_with_a_seen_signature_skip_the_guards(tmp_path, monkeypatch):
    """After arguments of one signature passed a variant's guards, calls with that signature go
    straight to its compiled function; other shapes, dtypes or scalar values still go through the
    guards to the variant that fits (or a new one), and each gets the right answer."""
    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", str(tmp_path))
    k = compile_kernel(_axpy, "axpy", _Consts(1.5))
    x, y = torch.arange(16.0), torch.full((16,), 2.0)
    assert float(k([x, y], 3.0)) == float((x * 1.5 + y * 3.0).sum())
    assert len(k.direct) == 1
    calls = []
    variant = k.variants[0]
    check = variant.guard_check
    monkeypatch.setattr(variant, "guard_check", lambda *a, **kw: calls.append(1) or check(*a, **kw))
    assert float(k([y, x], 3.0)) == float((y * 1.5 + x * 3.0).sum())
    assert calls == [], "a seen signature must not evaluate the guards again"
    x2 = torch.arange(8.0)
    assert float(k([x2, x2], 3.0)) == float((x2 * 4.5).sum())
    assert float(k([x.double(), y.double()], 3.0)) == float((x * 1.5 + y * 3.0).sum())
    assert len(k.variants) == 3 and len(k.direct) == 3
    assert float(k([x, y], 3.0)) == float((x * 1.5 + y * 3.0).sum())


def test_a_remembered_dataclass_signature_follows_its_fields():
    """A dataclass's signature is remembered while its fields hold the same objects; a field
    given another tensor or value is seen at once (the signature a fresh object would get)."""
    x, y = torch.zeros(16), torch.ones(16)
    pair = _Pair(x, y)
    first = kernels._signature(pair)
    assert kernels._signature(pair) is first, "remembered: the same fields give the same signature object"
    pair.b = torch.ones(16, dtype=torch.float64)
    assert kernels._signature(pair) == kernels._signature(_Pair(x, pair.b)) != first
    consts = _Consts(1.5)
    assert kernels._signature(consts) != kernels._signature(_Consts(2.5))
    object.__setattr__(consts, "scale", 2.5)
    assert kernels._signature(consts) == kernels._signature(_Consts(2.5))


def test_cache_can_be_switched_off(monkeypatch):
    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", "off")
    assert kernels.cache_dir() is None
    k = compile_kernel(_axpy, "axpy", _Consts(1.5))
    assert float(k([torch.ones(4), torch.ones(4)], 1.0)) == 10.0


def test_unwritable_cache_still_runs_the_kernel(tmp_path, monkeypatch, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache directory would go")
    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", str(blocker / "kernels"))
    with caplog.at_level(logging.WARNING, logger=kernels.__name__):
        k = compile_kernel(_axpy, "axpy", _Consts(1.5))
        assert float(k([torch.ones(4), torch.ones(4)], 1.0)) == 10.0
    assert "not saved" in caplog.text


_CONCURRENT = """
import logging, sys, torch
logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
from tests.workers.test_kernels import _Consts, _axpy
from workers.walk.kernels import compile_kernel
k = compile_kernel(_axpy, "axpy", _Consts(1.5))
print("result", float(k([torch.arange(8.0), torch.ones(8)], 2.0)))
"""


def test_processes_wanting_the_same_kernel_compile_it_once(tmp_path):
    """Two processes started together: one compiles (holding the artifact's lock), the other
    waits and loads what it saved."""
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, BSSRDF_KERNEL_CACHE=str(tmp_path))
    procs = [subprocess.Popen([sys.executable, "-c", _CONCURRENT], cwd=root, env=env, stdout=subprocess.PIPE, text=True) for _ in range(2)]
    outs = [p.communicate(timeout=300)[0] for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    text = "".join(outs)
    assert text.count("result 58.0") == 2
    assert text.count("compiled and saved") == 1 and text.count("kernel loaded from") == 1, text


def test_an_any_length_kernel_serves_every_chunk_length_from_one_artifact(tmp_path, monkeypatch):
    """any_length (the walk's step kernel: a shard's chunk, then its tail's shorter chunks): one
    compile and one artifact serve chunks of every length, in this kernel object and in a new
    one (as in a new process), with the eager function's results; the caller's tensors are not
    marked (a marked tensor fails a loaded kernel's guards), and the key leaves the length out."""
    monkeypatch.setenv("BSSRDF_KERNEL_CACHE", str(tmp_path))
    a, b = torch.zeros(112), torch.linspace(0.0, 1.0, 112)
    chunks = [_Pair(a[lo:hi], b[lo:hi]) for lo, hi in ((0, 64), (64, 96), (96, 112))]
    first = compile_kernel(_accumulate, "accumulate_any", any_length=True)
    assert float(first(chunks[0], 2.0)[0]) == float((b[:64] * 2.0).sum())
    assert float(first(chunks[1], 2.0)[0]) == float((b[64:96] * 2.0).sum())
    saved = sorted(tmp_path.glob("accumulate_any-*.pt2"))
    assert len(saved) == 1 and len(first.variants) == 1, "one compile for both lengths"
    stamp = saved[0].stat().st_mtime_ns
    loaded = compile_kernel(_accumulate, "accumulate_any", any_length=True)
    assert float(loaded(chunks[2], 2.0)[0]) == float((b[96:] * 2.0).sum())
    assert sorted(tmp_path.glob("accumulate_any-*.pt2")) == saved and saved[0].stat().st_mtime_ns == stamp, "loaded, not compiled"
    assert torch.equal(a, b * 2.0), "every chunk written in place, nothing else"
    assert not any(hasattr(t, "_dynamo_dynamic_indices") for c in chunks for t in (c.a, c.b))
    key = lambda n, any_length: artifact_key("k", None, (_Pair(torch.zeros(n), torch.zeros(n)), 2.0), any_length)  # noqa: E731
    assert key(64, True) == key(32, True) != key(64, False) != key(32, False)
