"""Compiled kernels that load in milliseconds: numba's machine code, kept as a shared
library (or an object file) and loaded without numba.

numba's own cache (``cache=True``) saves the compile, not the start-up: a fresh process
pays numba's import (0.16-0.32 s on the 2-core VM) and, at a kernel's first call, its
typing and lowering registries (0.36-0.6 s) before the first word, which on a 100 M-word
capture is as long as the loop itself. Here numba compiles a kernel once as a C callback
(pointers and sizes in, nothing out: no Python object, no allocation, nothing that can
raise) and its code is kept beside numba's cache: linked into a shared library by the
system's C compiler or linker where there is one (a later process loads it with ctypes in
a millisecond), and as an object file that llvmlite's MCJIT loads where there is none
(what numba itself does with its cache, less numba: 30-100 ms). Either way it is called
through ctypes, which releases the GIL. The entry is keyed by the kernel's source module,
this module, numba, llvmlite, Python and the host CPU; any failure falls back to numba's
dispatcher, which runs the same kernel body (the tests hold both to the numpy twin).

Environment: ``TCSPC_NATIVE=0`` turns this off (numba's dispatcher only).
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import platform
import re
import shutil
import sys
import threading
from collections.abc import Callable
from pathlib import Path

# A C callback's code declares the helpers of its error path (numba's GIL and exception
# helpers, NRT's destructor call), which these kernels never take (they cannot raise, and
# their arrays own no memory). Those declarations get bodies that trap, internal to the
# object: it then needs nothing numba would provide, and nothing is added to the process's
# symbol table (which numba's own JIT reads: a stub there would be called by numba's code).
_DECLARE = re.compile(r"^declare (.*?) (@\S+?)\((.*)\)(.*)$")


def _self_contained(ir: str) -> str:
    """``ir`` with every non-intrinsic declaration defined as a trap."""
    lines, trap = [], False
    for line in ir.splitlines():
        m = _DECLARE.match(line)
        if m and not m.group(2).lstrip("@\"").startswith("llvm."):
            ret, name, params, rest = m.groups()
            lines += [f"define internal {ret} {name}({params}){rest} {{",
                      "  call void @llvm.trap()", "  unreachable", "}"]
            trap = True
        else:
            lines.append(line)
    if trap and "@llvm.trap()" not in ir:
        lines.append("declare void @llvm.trap()")
    return "\n".join(lines) + "\n"


_lock = threading.Lock()
_engines: list = []  # the MCJIT engines and libraries of the loaded kernels, kept
_loaded: dict[str, Callable | None] = {}
#: why a kernel could not be had natively (name -> error), for diagnostics and tests
failures: dict[str, str] = {}


def enabled() -> bool:
    return os.environ.get("TCSPC_NATIVE", "1") != "0"


def _cache_dir(module_file: str) -> Path | None:
    """Where numba would cache a module's kernels: NUMBA_CACHE_DIR, else its __pycache__,
    else (a read-only install) the user's cache directory; None when none is writable."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    xdg = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    for d in ([Path(env)] if env else [Path(module_file).parent / "__pycache__",
                                        Path(xdg) / "tcspc-lidar"]):
        try:
            d.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(d, os.W_OK):
            return d
    return None


def _host() -> str:
    """The CPU the code is compiled for, without importing llvmlite."""
    try:
        info = Path("/proc/cpuinfo").read_text().split("\n\n", 1)[0]
        return "\n".join(ln for ln in info.splitlines()
                         if ln.split(":")[0].strip() in ("model name", "flags", "vendor_id"))
    except OSError:
        return platform.processor() + platform.machine()


def _version_file(package: str) -> bytes:
    import importlib.util

    spec = importlib.util.find_spec(package)
    return Path(spec.origin).with_name("_version.py").read_bytes()


def _key(name: str, module_file: str) -> str:
    h = hashlib.sha256()
    for part in (Path(module_file).read_bytes(), Path(__file__).read_bytes(),
                 # numba's and llvmlite's version files, read rather than imported
                 _version_file("numba"), _version_file("llvmlite"), name.encode(),
                 sys.version.encode(), sys.platform.encode(), platform.machine().encode(),
                 _host().encode()):
        h.update(part + b"\0")
    return h.hexdigest()[:20]


def _binding():
    import llvmlite.binding as ll

    ll.initialize_native_target()
    ll.initialize_native_asmprinter()
    return ll


def _map(ll, obj: bytes, symbol: str, argtypes) -> Callable:
    tm = ll.Target.from_default_triple().create_target_machine()
    engine = ll.create_mcjit_compiler(ll.parse_assembly(""), tm)
    _engines.append(engine)
    engine.add_object_file(ll.ObjectFileRef.from_data(obj))
    engine.finalize_object()
    addr = engine.get_function_address(symbol)
    if not addr:
        raise RuntimeError(f"{symbol} not found in its object code")
    return ctypes.CFUNCTYPE(None, *argtypes)(addr)


def _shared(path: Path, symbol: str, argtypes) -> Callable:
    lib = ctypes.CDLL(str(path))
    _engines.append(lib)
    fn = lib[symbol]
    fn.argtypes, fn.restype = argtypes, None
    return fn


def _link(ll, mod, so_path: Path) -> bool:
    """Link ``mod`` into a shared library at ``so_path``: position-independent code for
    the host CPU, linked by the system's C compiler or linker (False where none is)."""
    linker = shutil.which("cc") or shutil.which("gcc") or shutil.which("ld")
    if linker is None:
        return False
    import subprocess  # (only where a kernel is built: not at every command's start)
    tm = ll.Target.from_triple(mod.triple).create_target_machine(
        cpu=ll.get_host_cpu_name(), features=ll.get_host_cpu_features().flatten(), opt=3,
        reloc="pic", codemodel="default")
    tag = f"{os.getpid()}-{threading.get_ident()}"
    obj = so_path.with_name(f".{so_path.name}.{tag}.o")
    tmp = so_path.with_name(f".{so_path.name}.{tag}")
    try:
        obj.write_bytes(tm.emit_object(mod))
        res = subprocess.run([linker, "-shared", "-o", str(tmp), str(obj)],
                             capture_output=True, timeout=120)
        if res.returncode != 0:
            return False
        os.replace(tmp, so_path)
        return True
    finally:
        obj.unlink(missing_ok=True)
        tmp.unlink(missing_ok=True)


def kernel(name: str, module_file: str, argtypes: list, build: Callable) -> Callable | None:
    """The C kernel ``name`` as a ctypes function, or None where it cannot be had.

    ``build()`` compiles it (numba imported then) and returns ``numba.cfunc``'s result;
    ``argtypes`` are the ctypes types of its arguments (pointers as ``c_void_p``).
    """
    if not enabled():
        return None
    with _lock:
        if name in _loaded:
            return _loaded[name]
        fn = None
        try:
            d = _cache_dir(module_file)
            if d is None:  # nowhere to keep it: numba's dispatcher (and its cache)
                raise RuntimeError("no writable cache directory")
            base = d / f"{Path(module_file).stem}.{name}-{_key(name, module_file)}"
            so_path, obj_path, info_path = (base.with_name(base.name + ext)
                                            for ext in (".so", ".o", ".json"))
            if info_path.is_file():
                info = json.loads(info_path.read_text())
                if info.get("shared") and so_path.is_file():
                    try:
                        fn = _shared(so_path, info["symbol"], argtypes)
                    except OSError:  # (a library that does not load here: the object)
                        fn = None
                if fn is None:
                    fn = _map(_binding(), obj_path.read_bytes(), info["symbol"], argtypes)
            else:
                ll = _binding()
                cf = build()
                lib = cf._library
                mod = ll.parse_assembly(_self_contained(str(lib._final_module)))
                mod.verify()
                # object code as numba's own cache holds it (numba's JIT target machine)
                obj = lib._codegen._tm.emit_object(mod)
                info = {"symbol": cf.native_name, "shared": _link(ll, mod, so_path)}
                _write(obj_path, obj)  # the code first, then its index: a reader sees both
                _write(info_path, json.dumps(info).encode())
                fn = (_shared(so_path, info["symbol"], argtypes) if info["shared"] else
                      _map(ll, obj, info["symbol"], argtypes))
        except Exception as exc:  # noqa: BLE001 - any failure: numba's dispatcher instead
            failures[name] = f"{type(exc).__name__}: {exc}"
            fn = None
        _loaded[name] = fn
        return fn


def _write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}-{threading.get_ident()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)
