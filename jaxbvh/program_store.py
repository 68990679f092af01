"""Traced programs kept on disk, so that a warm process skips tracing and lowering too.

JAX's persistent cache (:mod:`jaxbvh.compile_cache`) keeps what XLA *compiled*; every new
process still traces each program in Python and lowers it to StableHLO before it can
look the compiled code up. For our large programs (an optimizer's loop of steps, the
SBVH level loop) that is most of a warm first call: the README script spent 3.5 of its
7.0 warm CPU s tracing and lowering (bench/results/bench_compile.md). This module keeps
each lowered program as a serialized :mod:`jax.export` artifact beside the compiled
ones; a later process deserializes it (milliseconds), and its compiled code comes from
JAX's cache as before.

:func:`stored_jit` is :func:`jax.jit` for the library's own top-level programs. A call
with concrete arguments is keyed by everything that decides what the program is: the
function's module and name, its static arguments (by value), the pytree structure and
the shapes and dtypes of its array arguments, the jaxbvh sources (a fingerprint of every
``.py`` file of the package: any code change makes new keys), JAX's version, the
platform and ``jax_enable_x64``. A process with several devices (sharded batches) compiles
as usual: an exported program is pinned to the devices it was exported for. Anything that cannot be keyed so (a static argument or
pytree node whose ``repr`` is not a value, such as a closure) and every call made while
tracing (inside a user's ``jit``, ``vmap`` or ``grad``) goes to plain :func:`jax.jit`,
which gives the same results: the store is only ever a shortcut to the same program.

Each program is compiled with the XLA options of its family under jaxbvh's compile policy
(:mod:`jaxbvh.compile_policy`; ``stored_jit(..., family=...)``, else by module): the
plain jit and the deserialized program alike, each option set its own program in memory
and in JAX's persistent cache (whose key includes the options). The stored file is the
lowered program, which the options do not change, so its key leaves them out.

The compiled code is kept too, beside the lowered program (``.jaxexe``, keyed also by the
XLA options, ``XLA_FLAGS``, the backend's version and the host CPU's model and flags): a
warm process loads it directly and so skips lowering and JAX's cache lookup as well (the
pipeline's first pass on spot, warm: 1.35-1.47 -> 0.96-1.11 CPU s). Only code XLA compiled
in this process is kept: an executable JAX's cache loaded and serialized again lost its
kernels (jaxlib 0.10's CPU client), so a program JAX's cache serves keeps that path. A
kept executable XLA refuses to start is removed and the program goes through JAX's cache;
a program that calls LAPACK always does (lowering sets up JAX's LAPACK kernels).

Rules: on while jaxbvh's compilation cache is on, in ``programs/`` of its folder
(:func:`store_dir`: off with that cache, and in a process with several devices); files are
written atomically (:func:`jaxbvh.files.atomic_write`); an unreadable or stale file is
replaced, never trusted; the folder is kept under :data:`MAX_STORE_BYTES` (the programs
used longest ago out first: the rule of every jaxbvh cache, :func:`jaxbvh.files.trim_least_recent`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import inspect
import os
import pickle
import threading
import time
import importlib.util
import warnings
import weakref
import zlib
from pathlib import Path

import jax

from jaxbvh import compile_cache, compile_policy
from jaxbvh.files import atomic_write, trim_least_recent

__all__ = ["EXECUTABLE_LOAD_EVENT", "MAX_STORE_BYTES", "StoredFunction", "clear_memory", "store_dir", "stored_jit"]

#: the folder is kept under this size (bytes), the programs used longest ago out first
#: (:func:`jaxbvh.files.trim_least_recent`). A stored program takes ~10-300 kB (a day's
#: work here: 678 programs, 29 MB).
MAX_STORE_BYTES = 512 * 1024 ** 2

#: bump when the file layout changes
_FORMAT = b"jaxbvh-program-store-1"

_SUFFIX = ".jaxprog"

#: a stored program's compiled code for one machine and option set (:func:`_executable_key`),
#: zlib-compressed at :data:`_EXECUTABLE_ZLIB_LEVEL`: the pipeline's nine programs take 1.4 MB
#: instead of 6.5, for 17 ms more to load them all (0.7 s)
_EXECUTABLE_FORMAT = b"jaxbvh-executable-2"
_EXECUTABLE_ZLIB_LEVEL = 3
_EXECUTABLE_SUFFIX = ".jaxexe"

#: the JAX monitoring event (seconds) of each compiled program loaded from the store
EXECUTABLE_LOAD_EVENT = "/jaxbvh/program_store/executable_load_sec"


#: every StoredFunction, for :func:`clear_memory`
_ALL: weakref.WeakSet = weakref.WeakSet()


@functools.cache
def _can_serialize() -> bool:
    # jax.export writes its files with flatbuffers (a dependency of jaxbvh; without it
    # every program is compiled as usual)
    return importlib.util.find_spec("flatbuffers") is not None


def store_dir() -> Path | None:
    """The folder of stored programs: ``programs/`` in the folder of jaxbvh's compilation
    cache while that cache is on (:mod:`jaxbvh.compile_cache`); None (the store is off)
    when it is off (``JAXBVH_CACHE=off``, :func:`jaxbvh.compile_cache.disable`, or a JAX
    cache the user configured, whose folder jaxbvh does not write to)."""
    folder = compile_cache.status()
    if folder["owner"] != "jaxbvh" or compile_cache.switched_off() or not _can_serialize():
        return None
    if jax.device_count() > 1:
        # several devices: an exported program is pinned to the devices it was exported
        # for and its outputs are committed to them, which a later program over all the
        # devices (a sharded batch) refuses; such a process compiles as usual
        return None
    return Path(folder["folder"]) / "programs"


@functools.cache
def _fingerprint() -> str:
    """A hash of every ``.py`` file of the jaxbvh package (paths and bytes)."""
    root = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _environment() -> str:
    import jaxlib

    return "|".join((jax.__version__, jaxlib.__version__, jax.default_backend(), str(jax.device_count()),
                     str(jax.config.jax_enable_x64), str(jax.config.jax_numpy_dtype_promotion),
                     str(jax.config.jax_default_matmul_precision)))


class _Unkeyable(Exception):
    """This call's program cannot be named by value: plain jit serves it."""


def _value_repr(value) -> str:
    """``value`` as text that names it across processes, or :class:`_Unkeyable`."""
    if isinstance(value, functools.partial):
        return (f"partial({_value_repr(value.func)}, {[_value_repr(a) for a in value.args]}, "
                f"{ {k: _value_repr(v) for k, v in sorted(value.keywords.items())} })")
    if inspect.isfunction(value) or inspect.isbuiltin(value):
        module = inspect.getmodule(value)
        name = getattr(value, "__qualname__", "")
        # a module-level function: its module and name say which code runs
        if module is not None and "<" not in name and getattr(module, name.split(".")[0], None) is not None:
            return f"{module.__name__}.{name}"
        raise _Unkeyable(name)
    text = repr(value)
    if " at 0x" in text or "object at" in text:
        raise _Unkeyable(text)
    return f"{type(value).__module__}.{type(value).__qualname__}:{text}"


class StoredFunction:
    """A jitted function whose lowered programs are kept in :func:`store_dir` (module
    docstring). Call it as the function; ``.jitted`` is the plain :func:`jax.jit`."""

    def __init__(self, fun, *, static_argnums=(), static_argnames=(), family=None):
        self.fun = fun
        #: the program family, which names its XLA options (:mod:`jaxbvh.compile_policy`)
        self.family = compile_policy.family_of(fun.__module__) if family is None else family
        compile_policy.options(self.family)  # an unknown family fails here, not at the first call
        # None, not (), for the one not given: jax.jit then finds the other from the
        # signature, so a static argument passed by position or by name stays static
        self._jit_args = dict(static_argnums=None if static_argnums == () else static_argnums,
                              static_argnames=None if static_argnames == () else static_argnames)
        self._jits: dict = {}  # options key -> plain jax.jit with those compiler options
        functools.update_wrapper(self, fun)
        self._signature = inspect.signature(fun)
        params = list(self._signature.parameters.values())
        nums = (static_argnums,) if isinstance(static_argnums, int) else tuple(static_argnums)
        names = (static_argnames,) if isinstance(static_argnames, str) else tuple(static_argnames)
        self._static = {params[i].name for i in nums} | set(names)
        self._plain_only = any(p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD) for p in params)
        self._memo: dict = {}
        self._name = f"{fun.__module__}.{fun.__qualname__}"
        self._warned = False
        _ALL.add(self)

    def compiler_options(self) -> dict:
        """The XLA options this function's programs get now (:func:`jaxbvh.compile_policy.options`)."""
        return compile_policy.options(self.family)

    @property
    def jitted(self):
        """The plain :func:`jax.jit` of the function, with the compiler options in force."""
        return self._jit_for(_options_key(self.compiler_options()))

    def _jit_for(self, options: tuple):
        jitted = self._jits.get(options)
        if jitted is None:
            jitted = jax.jit(self.fun, compiler_options=dict(options) or None, **self._jit_args)
            self._jits[options] = jitted
        return jitted

    def lower(self, *args, **kwargs):
        """:meth:`jax.stages.Wrapped.lower` of the plain jit."""
        return self.jitted.lower(*args, **kwargs)

    def _cache_size(self) -> int:
        """Programs this process holds for the function (stored ones and plain jit's)."""
        return len(self._memo) + sum(j._cache_size() for j in self._jits.values())

    def clear_cache(self) -> None:
        """Forget the programs held in memory (the stored files stay: a test that
        changes a constant read at trace time sets ``JAXBVH_CACHE=off`` as well)."""
        self._memo.clear()
        for jitted in self._jits.values():
            jitted.clear_cache()

    def __call__(self, *args, **kwargs):
        if not _top_level():
            # inside a transformation (a user's jit, vmap, grad, or one of our programs):
            # traced into that program, which has its own options (JAX refuses
            # compiler options on a nested jit)
            return self._jit_for(())(*args, **kwargs)
        options = _options_key(self.compiler_options())
        jitted = self._jit_for(options)
        if self._plain_only:
            return jitted(*args, **kwargs)
        folder = store_dir()
        if folder is None:
            return jitted(*args, **kwargs)
        bound = self._signature.bind(*args, **kwargs)
        bound.apply_defaults()
        dynamic = {k: v for k, v in bound.arguments.items() if k not in self._static}
        leaves, treedef = jax.tree_util.tree_flatten(dynamic)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return self._jit_for(())(*args, **kwargs)  # inside someone's transformation
        if any(isinstance(x, jax.Array) and not isinstance(x.sharding, jax.sharding.SingleDeviceSharding)
               for x in leaves):
            return jitted(*args, **kwargs)  # a program over several devices: compiled as usual
        try:
            static = tuple((k, _value_repr(v)) for k, v in bound.arguments.items() if k in self._static)
            avals = tuple(str(jax.typeof(x)) for x in leaves)
            # the options too: each option set is its own compiled program
            memo_key = (treedef, avals, static, options)
        except (_Unkeyable, TypeError):
            return jitted(*args, **kwargs)
        program = self._memo.get(memo_key)
        if program is None:
            program = self._program(folder, bound, treedef, leaves, avals, static, options)
            self._memo[memo_key] = program
        return program(leaves)

    def _program(self, folder: Path, bound, treedef, leaves, avals, static, options: tuple):
        """The callable ``leaves -> outputs`` for this key: loaded, or exported and stored.

        The file's key leaves the compiler options out on purpose: the stored artifact is
        the lowered program, the same under every option set; the options are given
        to the jit that compiles it here, and JAX's persistent cache keys its compiled
        code by them (its key includes the compile options and ``XLA_FLAGS``)."""
        text = repr((self._name, static, str(treedef), avals))
        if " at 0x" in text:
            return self._plain(bound, treedef, options)
        key = hashlib.sha256("\n".join((_fingerprint(), _environment(), text)).encode()).hexdigest()
        path = folder / f"{key[:2]}" / f"{key}{_SUFFIX}"
        loaded = _read(path)
        if loaded is None:
            try:
                loaded = self._export(bound, treedef, leaves)
            except Exception as exc:  # noqa: BLE001 - any export failure: plain jit, same results
                if not self._warned:
                    self._warned = True
                    warnings.warn(f"{self._name}: program not stored ({type(exc).__name__}: {exc}); "
                                  "compiling it as usual", RuntimeWarning, stacklevel=4)
                return self._plain(bound, treedef, options)
            _write(path, loaded)
        out_treedef, blob = loaded
        lapack_free = _LAPACK_MARK not in blob
        # a LAPACK-free program's compiled code is kept too (:func:`_write_executable`), so
        # that a warm process skips lowering and JAX's cache lookup; one with LAPACK calls
        # needs JAX's LAPACK set-up, which lowering does: it keeps the path through JAX's cache
        executable = path.with_name(f"{key}-{_executable_key(options)}{_EXECUTABLE_SUFFIX}") if lapack_free else None
        compiled = _read_executable(executable) if lapack_free else None
        through_jax = None

        def jax_path():
            exported = jax.export.deserialize(bytearray(blob))
            return jax.jit(exported.call, compiler_options=dict(options) or None)

        if compiled is None:
            through_jax = jax_path()
            if lapack_free:
                compiled = _compile_and_keep(through_jax, leaves, executable)

        def program(leaves):
            nonlocal compiled, through_jax
            if compiled is not None:
                try:
                    return jax.tree_util.tree_unflatten(out_treedef, compiled(*leaves))
                except jax.errors.JaxRuntimeError as exc:
                    if not str(exc).startswith(_DISPATCH_FAILED):
                        raise
                    # refused before it ran (a kept executable XLA cannot run): the file
                    # goes, the program comes through JAX's cache from now on
                    with contextlib.suppress(OSError):
                        executable.unlink()
                    compiled = None
                    through_jax = through_jax or jax_path()
            with _lapack_left_alone(lapack_free):
                return jax.tree_util.tree_unflatten(out_treedef, through_jax(*leaves))

        return program

    def _rebuild(self, bound, treedef):
        """``leaves -> (args, kwargs)`` of this call with its dynamic leaves replaced."""
        static = {k: v for k, v in bound.arguments.items() if k in self._static}
        names = list(bound.arguments)

        def rebuild(leaves):
            arguments = dict(static)
            arguments.update(jax.tree_util.tree_unflatten(treedef, leaves))
            call = inspect.BoundArguments(self._signature, {k: arguments[k] for k in names})
            return call.args, call.kwargs

        return rebuild

    def _plain(self, bound, treedef, options: tuple):
        rebuild = self._rebuild(bound, treedef)
        jitted = self._jit_for(options)

        def program(leaves):
            args, kwargs = rebuild(leaves)
            return jitted(*args, **kwargs)

        return program

    def _export(self, bound, treedef, leaves):
        """Trace and lower this call's program; returns ``(output treedef, bytes)``."""
        rebuild = self._rebuild(bound, treedef)
        out = []

        def flat(*flat_leaves):
            args, kwargs = rebuild(flat_leaves)
            result_leaves, result_treedef = jax.tree_util.tree_flatten(self.fun(*args, **kwargs))
            out.append(result_treedef)
            return result_leaves

        exported = jax.export.export(jax.jit(flat))(*leaves)
        return out[0], bytes(exported.serialize())


def stored_jit(fun=None, *, static_argnums=(), static_argnames=(), family=None):
    """:func:`jax.jit` with the lowered programs kept on disk (module docstring); use as
    ``@stored_jit`` or ``@partial(stored_jit, static_argnames=(...))``. ``family``: the
    program family that names its XLA options, ``"once"`` or ``"loop"``
    (:mod:`jaxbvh.compile_policy`; None: by the function's module,
    :func:`jaxbvh.compile_policy.family_of`)."""
    if fun is None:
        return functools.partial(stored_jit, static_argnums=static_argnums, static_argnames=static_argnames,
                                 family=family)
    return StoredFunction(fun, static_argnums=static_argnums, static_argnames=static_argnames, family=family)


#: the bytes every LAPACK call of a lowered program names (its custom-call targets,
#: ``lapack_sgetrf_ffi`` ...); a stored program without them calls no LAPACK
_LAPACK_MARK = b"lapack"

#: set while a LAPACK-free stored program is lowered (:func:`_lapack_left_alone`)
_lapack_skip = threading.local()


@functools.cache
def _install_lapack_guard() -> bool:
    """Let :func:`_lapack_left_alone` skip JAX's LAPACK set-up for our programs.

    Before lowering any exported program on a CPU, JAX sets up its LAPACK kernels
    (``jax._src.export._export._ensure_backends_initialized``), which imports
    ``scipy.linalg`` (~270 modules, 0.3-0.5 CPU s here): a warm process paid it at its
    first stored program, though none of ours calls LAPACK (the SBVH build's warm call
    1.3-1.6 CPU s, of which that import 0.3-0.5). JAX's own lowering of a LAPACK
    operation sets LAPACK up itself when it meets one, so skipping it here for a program
    without LAPACK calls leaves every other program as it was. False (nothing changed)
    when this JAX has no such function."""
    try:
        from jax._src.export import _export  # no public spelling in JAX 0.10
        original = _export._ensure_backends_initialized
    except (ImportError, AttributeError):
        return False

    def ensure_backends_initialized(platforms):
        if not getattr(_lapack_skip, "on", False):
            original(platforms)

    _export._ensure_backends_initialized = ensure_backends_initialized
    return True


@contextlib.contextmanager
def _lapack_left_alone(lapack_free: bool):
    """Within: lowering a stored program skips JAX's LAPACK set-up if ``lapack_free``."""
    if not lapack_free or not _install_lapack_guard():
        yield
        return
    before = getattr(_lapack_skip, "on", False)
    _lapack_skip.on = True
    try:
        yield
    finally:
        _lapack_skip.on = before


def _top_level() -> bool:
    """True outside every JAX transformation (no trace in progress)."""
    from jax._src import core  # no public spelling in JAX 0.10; without it, tracers are the test

    clean = getattr(core, "trace_state_clean", None)
    return True if clean is None else clean()


def _options_key(options: dict) -> tuple:
    """Compiler options as a sorted tuple of items (a dict key)."""
    return tuple(sorted(options.items()))


def clear_memory() -> None:
    """Forget the programs held in memory by every :class:`StoredFunction` (the files stay)."""
    for fun in list(_ALL):
        fun._memo.clear()


def _read(path: Path):
    """``(out treedef, bytes)`` from ``path``, or None when absent or unreadable (then removed)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    try:
        if not data.startswith(_FORMAT):
            raise ValueError("not a stored program")
        out_treedef, blob = pickle.loads(data[len(_FORMAT):])
        os.utime(path)  # recently used: evicted last
        return out_treedef, blob
    except Exception:  # noqa: BLE001 - a damaged or foreign file is replaced, never trusted
        with contextlib.suppress(OSError):
            path.unlink()
        return None


def _write(path: Path, loaded) -> None:
    _write_bytes(path, _FORMAT + pickle.dumps(loaded))


def _write_bytes(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_write(path) as f:
            f.write(data)
        store = path.parent.parent
        trim_least_recent([*store.glob(f"*/*{_SUFFIX}"), *store.glob(f"*/*{_EXECUTABLE_SUFFIX}")],
                          MAX_STORE_BYTES, keep=path)
    except OSError:
        pass  # a read-only or full disk: the program still runs, it is just not kept


@functools.cache
def _machine() -> str:
    """What the compiled code was made for beyond JAX's versions: the backend's platform
    version and device kind, and the host CPU's model and instruction-set flags (a
    folder shared between machines never hands one machine another's code)."""
    device = jax.devices()[0]
    cpu = ""
    with contextlib.suppress(OSError):
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        cpu = "|".join(sorted({line for line in lines if line.startswith(("model name", "flags"))}))
    if not cpu:
        import platform
        cpu = f"{platform.machine()}|{platform.processor()}"
    return "|".join((device.client.platform_version, device.device_kind, cpu))


def _executable_key(options: tuple) -> str:
    """What decides a stored program's compiled code besides the program itself: its
    XLA options, ``XLA_FLAGS`` and the machine (:func:`_machine`)."""
    text = repr((options, os.environ.get("XLA_FLAGS", ""), _machine()))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def _read_executable(path: Path):
    """The compiled program kept at ``path`` (a :class:`jax.stages.Compiled`), or None
    when absent or unloadable (then removed)."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    from jax.experimental import serialize_executable
    start = time.perf_counter()
    try:
        if not data.startswith(_EXECUTABLE_FORMAT):
            raise ValueError("not a stored executable")
        payload, in_tree, out_tree = pickle.loads(zlib.decompress(data[len(_EXECUTABLE_FORMAT):]))
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # noqa: BLE001 - a damaged or foreign file is replaced, never trusted
        with contextlib.suppress(OSError):
            path.unlink()
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used: evicted last
    jax.monitoring.record_event_duration_secs(EXECUTABLE_LOAD_EVENT, time.perf_counter() - start)
    return compiled


#: how XLA says a loaded executable could not start (``JaxRuntimeError`` text)
_DISPATCH_FAILED = "INTERNAL: Error dispatching computation"

#: ``seen``: JAX's persistent cache served a compile in this thread since it was reset
_cache_hit = threading.local()


@functools.cache
def _listen_for_cache_hits() -> None:
    def listener(event, **kwargs):
        if event == "/jax/compilation_cache/cache_hits":
            _cache_hit.seen = True

    jax.monitoring.register_event_listener(listener)


def _compile_and_keep(jitted, leaves, path: Path):
    """``jitted`` compiled for ``leaves`` (or loaded from JAX's cache); the compiled code
    is written to ``path`` only when XLA compiled it here: an executable loaded from
    JAX's cache and serialized again lost its kernels (XLA's CPU client in jaxlib 0.10:
    "Function ... not found" at its first call in the next process)."""
    _listen_for_cache_hits()
    _cache_hit.seen = False
    with _lapack_left_alone(True):
        compiled = jitted.lower(*leaves).compile()
    if not _cache_hit.seen:
        _write_executable(path, compiled)
    return compiled


def _write_executable(path: Path, compiled) -> None:
    from jax.experimental import serialize_executable
    try:
        payload, in_tree, out_tree = serialize_executable.serialize(compiled)
        data = _EXECUTABLE_FORMAT + zlib.compress(pickle.dumps((payload, in_tree, out_tree)), _EXECUTABLE_ZLIB_LEVEL)
    except Exception:  # noqa: BLE001 - a program XLA cannot serialize is compiled in every process
        return
    _write_bytes(path, data)


