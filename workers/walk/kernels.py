"""Compiled kernels of the walk, saved whole so that a new process starts without tracing.

torch.compile keeps inductor's generated code in an on-disk cache, but every new process still
has dynamo trace the Python function before it can look that code up: 4-11 s per process for the
8-step walk and its refill on the machines measured (BENCHMARKS.md).  A worker process pays this on
every start, which is what kept two workers from scaling end to end.  torch's ahead-of-time
compile (``torch.compile(fn).aot_compile``) serializes the traced and compiled function; a new
process loads it instead of tracing.

An artifact is keyed by everything that shapes the generated code:
- the kernel's name and static constants (the WalkParams, steps per call, ...);
- the kind, dtype and shape of every argument (tensors inside lists and dataclasses included;
  not the length of a kernel compiled for any length, see :func:`compile_kernel`) and the values
  of non-tensor arguments (they are baked into the graph);
- torch and Python versions, the CPU's vector capability (an AVX-512 kernel cannot run on an
  AVX2 machine sharing the cache), the torch thread count (the kernels differ for 1 and more
  threads) and grad mode;
- a digest of the source of the modules the graphs are traced from (GRAPH_MODULES).

Artifacts live in ``$BSSRDF_KERNEL_CACHE`` (default ``$XDG_CACHE_HOME/bssrdf-db/kernels``, else
``~/.cache/bssrdf-db/kernels``) and are written atomically; of several processes wanting the
same missing kernel one compiles it (under a file lock) and the others wait and load it.
``BSSRDF_KERNEL_CACHE=off`` compiles in-process with plain torch.compile.  An artifact that fails to load is compiled again and replaced.  A kernel
compiled ahead of time does not share inductor's graph cache: the first use of a new kernel on a
machine costs a full compile (one to two minutes for the 8-step walk) once.

Whoever shows progress can learn that a compile is under way (a worker reports it in its
heartbeats, so the job's page says "compiling" instead of "0 photons/s"):

    with observe_compiles(lambda name, compiling: ...):   # (kernel name, True at start / False at end)
        run_shard(...)

The callback runs in the compiling thread, around the compile itself (or the wait for another
process compiling the same artifact); loading a saved artifact is not reported.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import operator
import os
import sys
import threading
import weakref
from pathlib import Path
from typing import Any, Callable

import torch

from . import rng
from .engine import init_engine

__all__ = ["GRAPH_MODULES", "artifact_key", "cache_dir", "compile_kernel", "observe_compiles", "source_digest"]

log = logging.getLogger(__name__)

# Modules of this package whose code ends up in a compiled graph (tests check the import closure).
GRAPH_MODULES = ("walk", "connections", "hybrid", "stretch", "path_roulette", "harvest", "optics", "phase", "rng", "binning", "search", "conventions")

_compile_lock = threading.Lock()  # one compile at a time per process (threads sharing a kernel)
_observers: list[Callable[[str, bool], None]] = []  # observe_compiles callbacks, in registration order


@contextlib.contextmanager
def observe_compiles(callback: Callable[[str, bool], None]):
    """Call ``callback(kernel_name, True)`` when a kernel starts compiling and
    ``callback(kernel_name, False)`` when it is done (or failed), while the block runs."""
    _observers.append(callback)
    try:
        yield
    finally:
        _observers.remove(callback)


@contextlib.contextmanager
def _compiling(name: str):
    """Tell the observers that kernel ``name`` is compiling for the duration of the block; an
    observer's own error is logged, never raised into the walk."""
    def tell(state: bool) -> None:
        for callback in list(_observers):
            try:
                callback(name, state)
            except Exception:  # noqa: BLE001 - progress reporting must not break a compile
                log.exception("compile observer failed")

    tell(True)
    try:
        yield
    finally:
        tell(False)


INDUCTOR_CONFIG = {"max_fusion_size": 512, "size_asserts": False}
"""Inductor settings every kernel is compiled with (part of the artifact key).

- ``max_fusion_size``: the exit walk's call unrolls EXIT_STEPS_PER_CALL steps; with inductor's
  default (64 nodes) it emits about one loop over the lane arrays per step, and the step is
  bound by the memory traffic of those passes.  512 lets the unrolled steps fuse into fewer
  loops: paired on a 2-core Xeon (AVX-512), exit walk M1 +37-46 %, M2 +13-22 %, hybrid M1
  +38-51 % steps per CPU-second; the same tables to the bit and about the same compile time
  (BENCHMARKS.md).
- ``size_asserts`` off: the generated code would check the size and stride of every input on
  every call (~1 us each: ~25 us per harvest call with the 23 lane fields, 7 % of an M2 harvest
  call), which :class:`_Kernel` has already matched against the variant's signature before it
  calls the compiled function directly (a signature's first call goes through the variant's own
  guards, which check them)."""


def cache_dir() -> Path | None:
    """Where artifacts are kept, or None when the cache is switched off."""
    env = os.environ.get("BSSRDF_KERNEL_CACHE", "")
    if env.lower() in ("off", "0", "none", "no"):
        return None
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "bssrdf-db" / "kernels"


def source_digest() -> str:
    """sha256 over the source files of GRAPH_MODULES."""
    h = hashlib.sha256()
    here = Path(__file__).parent
    for name in GRAPH_MODULES:
        h.update(name.encode() + b"\0" + (here / f"{name}.py").read_bytes() + b"\0")
    return h.hexdigest()


def _describe(v: Any, any_length: bool = False) -> Any:
    """A hashable description of an argument: what the compiled graph is specialised on
    (with any_length, a tensor's first dimension is not: :func:`compile_kernel`'s any_length)."""
    if isinstance(v, torch.Tensor):
        shape = ("any", *v.shape[1:]) if any_length else tuple(v.shape)
        return ("tensor", str(v.dtype), shape, tuple(v.stride()), v.device.type)
    if isinstance(v, (list, tuple)):
        return (type(v).__name__, tuple(_describe(x, any_length) for x in v))
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return (type(v).__qualname__, tuple((f.name, _describe(getattr(v, f.name), any_length)) for f in dataclasses.fields(v)))
    if isinstance(v, (bool, int, float, str, type(None))):
        return (type(v).__name__, repr(v))
    raise TypeError(f"compile_kernel: cannot key an argument of type {type(v).__name__}")


def artifact_key(name: str, constants: Any, args: tuple, any_length: bool = False) -> str:
    """sha256 naming the artifact of kernel `name` with these constants, called with `args`
    (see the module docstring for what it covers; INDUCTOR_CONFIG is part of it, inductor
    settings from the environment are not; with any_length, the first argument's first
    dimension is left out: :func:`compile_kernel`)."""
    described = (_describe(args[0], True), *map(_describe, args[1:])) if any_length else _describe(args)
    parts = (
        name, repr(constants), described, any_length, torch.__version__, sys.version_info[:2], torch.backends.cpu.get_cpu_capability(),
        torch.get_num_threads(), torch.is_grad_enabled(), source_digest(), sorted(INDUCTOR_CONFIG.items()),
    )  # fmt: skip
    return hashlib.sha256(repr(parts).encode()).hexdigest()


def _signature(v: Any) -> Any:
    """What a compiled variant's guards check of an argument, cheaply: dtype, shape, stride and
    device of tensors, recursively through lists and dataclasses, and the values of scalars.
    (:func:`_describe` covers the same for the artifact key; this one runs on every call.)"""
    if isinstance(v, torch.Tensor):
        return (v.dtype, v.shape, v.stride(), v.is_cpu)
    if isinstance(v, (list, tuple)):
        return tuple(map(_signature, v))
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return _dataclass_signature(v)
    return (type(v), v)


_MAX_REMEMBERED = 64  # dataclass signatures kept (a shard passes the same few lane chunks and tables)
_remembered: dict[int, tuple[weakref.ref, tuple, Any]] = {}  # id -> (object, its fields, signature), weakly


class _Held:
    """A non-tensor field value remembered as it is, called like a weak reference."""

    __slots__ = ("value",)

    def __init__(self, value: Any):
        self.value = value

    def __call__(self) -> Any:
        return self.value


def _ref(x: Any) -> Callable[[], Any]:
    return weakref.ref(x) if isinstance(x, torch.Tensor) else _Held(x)


_getters: dict[type, Callable[[Any], tuple]] = {}  # dataclass type -> its field values as a tuple


def _field_values(v: Any) -> tuple:
    """The values of v's dataclass fields, in declaration order (one C-level attrgetter per type)."""
    get = _getters.get(type(v))
    if get is None:
        names = tuple(f.name for f in dataclasses.fields(v))
        if len(names) > 1:
            get = operator.attrgetter(*names)
        else:
            get = lambda x, names=names: tuple(getattr(x, n) for n in names)  # noqa: E731
        _getters[type(v)] = get
    return get(v)


def _dataclass_signature(v: Any) -> Any:
    """_signature of a dataclass, remembered for the object as long as every field still holds
    the same objects (checked by identity on each call; a tensor's dtype, shape and strides do
    not change in place here, where lanes are only written with copy_ and indexing).  The walk
    passes the same lane chunks and tables on every call; walking their ~20 fields in Python cost
    ~5 % of a short walk's shard, so the check runs in C (attrgetter, map over the references).
    Held by weak references: remembering keeps nothing alive."""
    values = _field_values(v)
    hit = _remembered.get(id(v))
    if hit is not None and hit[0]() is v and len(hit[1]) == len(values) and all(map(operator.is_, map(operator.call, hit[1]), values)):
        return hit[2]
    sig = (type(v), tuple(map(_signature, values)))
    if len(_remembered) >= _MAX_REMEMBERED:
        _remembered.clear()
    try:
        _remembered[id(v)] = (weakref.ref(v), tuple(map(_ref, values)), sig)
    except TypeError:  # a dataclass with __slots__ and no __weakref__: not remembered
        pass
    return sig


class _Kernel:
    """A function compiled on first call: loaded from its artifact, or compiled and saved.

    Each variant is specialised on the arguments it was first called with; a call whose
    arguments fail every variant's guards obtains one more.  Once arguments of a given
    :func:`_signature` have passed a variant's guards, later calls with that signature go to the
    variant's compiled function directly: the guard evaluation costs ~40 us a call, as much as
    a short kernel.
    """

    def __init__(self, fn: Callable, name: str, constants: Any, any_length: bool = False):
        self.fn, self.name, self.constants, self.any_length = fn, name, constants, any_length
        self.variants: list[Callable] = []
        self.direct: dict[Any, Callable] = {}
        self.lazy: set[int] = set()  # ids of variants that compile on their first call (no artifact cache)

    def __call__(self, *args):
        key = (_signature(args), torch.is_grad_enabled())
        direct = self.direct.get(key)
        if direct is not None:
            return direct(*args)
        variants = self.variants
        for i in range(len(variants) - 1, -1, -1):
            try:
                out = variants[i](*args)
            except RuntimeError as exc:  # arguments this variant was not compiled for
                if "GuardManager check failed" not in str(exc):
                    raise
                continue
            if i != len(variants) - 1:  # most recently used last: tried first next time
                self.variants = [*variants[:i], *variants[i + 1 :], variants[i]]
            self._remember(key, variants[i])
            return out
        with _compile_lock:
            if self.variants is variants:  # no other thread added one meanwhile
                self.variants = [*variants, self._obtain(args)]
        newest = self.variants[-1]
        if id(newest) in self.lazy:  # plain torch.compile: this first call compiles it
            self.lazy.discard(id(newest))
            with _compiling(self.name):
                out = newest(*args)
        else:
            out = newest(*args)
        self._remember(key, self.variants[-1])
        return out

    def _remember(self, key: Any, variant: Callable) -> None:
        """Send calls with this signature straight to the variant's compiled function (an
        artifact's; a plain torch.compile function keeps its own guard dispatch)."""
        fn = getattr(variant, "fn", None)
        if callable(fn) and hasattr(variant, "guard_check"):
            self.direct[key] = fn

    def _obtain(self, args: tuple) -> Callable:
        init_engine()  # the GIL-free binding template must be in place before inductor builds one
        rng.native_wide_multiply()  # decided outside the trace (the traced code only reads it)
        compiler = torch.compile(self.fn, fullgraph=True, dynamic=False, options=dict(INDUCTOR_CONFIG))
        directory = cache_dir()
        if directory is None or not hasattr(compiler, "aot_compile"):
            self.lazy.add(id(compiler))
            return compiler
        path = directory / f"{self.name}-{artifact_key(self.name, self.constants, args, self.any_length)[:24]}.pt2"
        stamp = _stamp(path)
        if stamp is not None and (loaded := _load(path)) is not None:
            return loaded
        # One process compiles a given artifact; others wanting it meanwhile wait, then load it.
        with _compiling(self.name), _file_lock(path):
            if _stamp(path) not in (None, stamp) and (loaded := _load(path)) is not None:
                return loaded
            with torch._inductor.config.patch(INDUCTOR_CONFIG):
                compiled = compiler.aot_compile((_any_length(args) if self.any_length else args, {}))
            try:
                compiled.save_compiled_function(str(path))
            except OSError as exc:  # e.g. a read-only home in a container: run, just do not keep it
                log.warning("kernel artifact %s not saved (%s: %s); set BSSRDF_KERNEL_CACHE to a writable directory", path, type(exc).__name__, exc)
            else:
                log.info("kernel %s compiled and saved to %s", self.name, path)
        return compiled


def _any_length(args: tuple) -> tuple:
    """The example arguments to compile with any length along the first argument's first
    dimension: that argument rebuilt with aliases of its tensors marked dynamic there (the
    caller's tensors stay unmarked: a tensor marked at run time fails the loaded kernel's guards)."""

    def alias(v: Any) -> Any:
        if isinstance(v, torch.Tensor):
            a = v.view(v.shape)
            torch._dynamo.mark_dynamic(a, 0)
            return a
        if isinstance(v, (list, tuple)):
            return type(v)(map(alias, v))
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return dataclasses.replace(v, **{f.name: alias(getattr(v, f.name)) for f in dataclasses.fields(v) if f.init})
        return v

    return (alias(args[0]), *args[1:])


def _stamp(path: Path) -> int | None:
    """Modification time of path in ns, None if it does not exist."""
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def _load(path: Path) -> Callable | None:
    """The compiled function saved at path, or None (with a warning) if it does not load."""
    try:
        # The artifact was built for this CPU capability (it is in the key): let inductor trust
        # the CPU flags for the base ISA instead of probe-building a program (saves ~0.5 s).
        with open(path, "rb") as f, torch._inductor.config.patch({"cpp.vec_isa_ok": True}):
            loaded = torch.compiler.load_compiled_function(f)
    except Exception as exc:  # noqa: BLE001 - any unreadable artifact is rebuilt
        log.warning("kernel artifact %s did not load (%s: %s); compiling it again", path, type(exc).__name__, exc)
        return None
    log.info("kernel loaded from %s", path)
    return loaded


@contextlib.contextmanager
def _file_lock(path: Path):
    """An exclusive lock on path + ".lock" (fcntl; released if the holder dies).  Where the
    directory cannot be created or locked, nothing is locked (compiling twice is only slower)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(f"{path}.lock", os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        yield
        return
    try:
        import fcntl

        fcntl.flock(fd, fcntl.LOCK_EX)
    except (ImportError, OSError):  # pragma: no cover - not POSIX, or a filesystem without locks
        pass
    try:
        yield
    finally:
        os.close(fd)  # closing releases the lock


def compile_kernel(fn: Callable, name: str, constants: Any = None, any_length: bool = False) -> Callable:
    """fn compiled for static shapes (fullgraph), kept on disk between processes.

    name and constants (anything with a faithful repr: the values fn closes over) identify the
    kernel; the arguments of the first call (and of any later call with other shapes) complete
    the key.  The artifact specialises on those shapes, so callers pass fixed-size chunks (but
    see any_length below).

    Arguments may be tensors, and lists and dataclasses of them, passed whole (a structure of
    arrays such as :class:`workers.walk.walk.Lanes` or a chunk of views into one): the guards read
    their fields, no pytree registration is needed, and in-place writes reach the viewed
    storage.  Results are tensors or tuples of them: a loaded artifact would rebuild a dataclass
    result by its class name, which ``load_compiled_function`` cannot resolve.

    any_length: the first argument's tensors are compiled for any length along their first
    dimension (one symbol; they must all have it).  The walk's step kernel takes a chunk of lanes,
    and a shard steps chunks of several lengths (its chunk, then its tail's shorter ones): one
    kernel serves them all, where a kernel per length cost a compile each (minutes on a slow
    core, BENCHMARKS.md).  The lengths must be multiples of the vector width (every chunk is a
    power of two of at least 128 lanes: workers.run.plan): lanes past the last multiple would
    run in the scalar loop, whose math functions may round differently from the vector ones, and
    a photon's result would then depend on its lane.
    """
    return _Kernel(fn, name, constants, any_length)
