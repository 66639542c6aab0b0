"""Mitsuba 3 / Dr.Jit backend: the only module of ngp-mi that imports ``mitsuba`` or ``drjit``.

Everything else asks this module for the two libraries (:func:`mitsuba`, :func:`drjit`), so that
the set-up below happens exactly once and before the first import:

1. **libLLVM discovery.** Dr.Jit's LLVM backend loads ``libLLVM`` at run time. LLVM 15 (Debian 12's
   default) aborts inside LLVM (``Cannot select: fminimum``); LLVM >= 16 works. We honour
   ``DRJIT_LIBLLVM_PATH`` and otherwise pick the newest ``libLLVM`` >= 16 from the usual library
   folders, then export ``DRJIT_LIBLLVM_PATH`` before ``drjit`` is imported.
2. **Variant choice.** ``cuda_ad_rgb`` when a CUDA device works, else ``llvm_ad_rgb``;
   ``NGP_MI_VARIANT`` overrides (any variant Mitsuba was built with).
3. **Threads.** Dr.Jit's LLVM backend defaults to one worker per core; ``NGP_MI_THREADS`` overrides.

With no usable backend, :func:`load` raises one :class:`BackendError` that says what to install.
Run ``python -m ngp_mi.backend`` to print the libLLVM that would be used (the Makefile does).
"""

from __future__ import annotations

import dataclasses
import gc
import glob
import os
import platform
import re
import sys
from pathlib import Path
from types import ModuleType
from typing import Iterable, Mapping

MIN_LLVM_VERSION = 16
ENV_LLVM = "DRJIT_LIBLLVM_PATH"
ENV_VARIANT = "NGP_MI_VARIANT"
ENV_THREADS = "NGP_MI_THREADS"
AUTO_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")

INSTALL_HINT = (
    "Install LLVM >= 16 (Debian/Ubuntu: `apt-get install libllvm19`; `make setup` does this), "
    f"or point {ENV_LLVM} at a libLLVM.so of version >= {MIN_LLVM_VERSION}."
)


class BackendError(RuntimeError):
    """No usable Mitsuba / Dr.Jit backend; the message says what to install or set."""


# --------------------------------------------------------------------------- libLLVM discovery

_VERSION_PATTERNS = (
    re.compile(r"LLVM-(\d+)"),          # libLLVM-19.so, libLLVM-14.0.6.so.1
    re.compile(r"LLVM\.so\.(\d+)"),     # libLLVM.so.19.1
    re.compile(r"LLVM\.(\d+)\.dylib"),  # libLLVM.19.dylib
    re.compile(r"llvm-(\d+)"),          # /usr/lib/llvm-19/lib/libLLVM.so
    re.compile(r"llvm@(\d+)"),          # Homebrew's llvm@19
)


def llvm_version(path: str | os.PathLike) -> int | None:
    """Major LLVM version encoded in a libLLVM file name, its link target or its folder; None if unknown."""
    path = Path(path)
    names = [path.name, Path(os.path.realpath(path)).name, *[p.name for p in path.parents][:3]]
    for name in names:
        for pattern in _VERSION_PATTERNS:
            match = pattern.search(name)
            if match:
                return int(match.group(1))
    return None


def default_llvm_search_dirs() -> list[str]:
    """Folders where distributions and Homebrew put libLLVM, most specific first."""
    arch = platform.machine()
    dirs = [
        *os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep),
        f"/usr/lib/{arch}-linux-gnu",
        *sorted(glob.glob("/usr/lib/llvm-*/lib"), reverse=True),
        "/usr/lib64", "/usr/lib", "/usr/local/lib",
        "/opt/homebrew/opt/llvm/lib", "/usr/local/opt/llvm/lib",
    ]
    return [d for d in dict.fromkeys(dirs) if d]


def _is_shared_libllvm(name: str) -> bool:
    return name.startswith("libLLVM") and (".so" in name or name.endswith(".dylib")) and not name.endswith(".a")


def find_libllvm(search_dirs: Iterable[str] | None = None, env: Mapping[str, str] | None = None) -> Path:
    """Return the libLLVM Dr.Jit should load.

    ``env[DRJIT_LIBLLVM_PATH]`` wins when set (it must exist, and must not be a known-broken
    LLVM < 16). Otherwise the newest libLLVM >= 16 in ``search_dirs`` is returned. Files whose
    version cannot be read are used only when no versioned candidate exists.
    """
    env = os.environ if env is None else env
    explicit = env.get(ENV_LLVM)
    if explicit:
        path = Path(explicit)
        if not path.is_file():
            raise BackendError(f"{ENV_LLVM}={explicit} does not exist. {INSTALL_HINT}")
        version = llvm_version(path)
        if version is not None and version < MIN_LLVM_VERSION:
            raise BackendError(
                f"{ENV_LLVM}={explicit} is LLVM {version}; Dr.Jit needs LLVM >= {MIN_LLVM_VERSION} "
                f"(LLVM 15 aborts with 'Cannot select: fminimum'). {INSTALL_HINT}")
        return path

    dirs = list(default_llvm_search_dirs() if search_dirs is None else search_dirs)
    seen: dict[str, tuple[int | None, Path]] = {}
    for folder in dirs:
        try:
            names = sorted(os.listdir(folder))
        except OSError:
            continue
        for name in names:
            if not _is_shared_libllvm(name):
                continue
            path = Path(folder) / name
            real = os.path.realpath(path)
            if real not in seen and os.path.isfile(real):
                seen[real] = (llvm_version(path), path)

    usable = [(v, p) for v, p in seen.values() if v is not None and v >= MIN_LLVM_VERSION]
    if usable:
        return max(usable, key=lambda vp: vp[0])[1]
    unknown = [p for v, p in seen.values() if v is None]
    if unknown:
        return unknown[0]
    found = ", ".join(f"{p} (LLVM {v})" for v, p in seen.values()) or "none"
    raise BackendError(
        f"No usable libLLVM (>= {MIN_LLVM_VERSION}) found in {', '.join(dirs)}; found: {found}. {INSTALL_HINT}")


# --------------------------------------------------------------------------- initialisation

@dataclasses.dataclass(frozen=True)
class Backend:
    """The initialised libraries and the choices made for them."""

    mi: ModuleType
    dr: ModuleType
    variant: str
    libllvm: Path | None
    threads: int

    @property
    def is_cuda(self) -> bool:
        return self.variant.startswith("cuda")


_backend: Backend | None = None


def _import_libraries() -> tuple[ModuleType, ModuleType]:
    # Imported here, not at the top: DRJIT_LIBLLVM_PATH and the thread count must be set first.
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise BackendError(
            f"Cannot import Mitsuba / Dr.Jit ({exc}). Install them with "
            "`pip install mitsuba==3.9.1 drjit==1.5.0` (`make setup` does this).") from exc
    return mi, dr


def _cuda_works(mi: ModuleType, dr: ModuleType) -> bool:
    if not dr.has_backend(dr.JitBackend.CUDA):
        return False
    try:
        mi.set_variant("cuda_ad_rgb")
        x = mi.Float(1.0) + 1.0
        dr.eval(x)
        return float(x[0]) == 2.0
    except Exception:  # a broken driver or no device: fall back to LLVM
        return False


def load(variant: str | None = None, threads: int | None = None) -> Backend:
    """Initialise Mitsuba / Dr.Jit once and return the :class:`Backend`.

    ``variant`` / ``threads`` default to ``$NGP_MI_VARIANT`` / ``$NGP_MI_THREADS`` and then to the
    automatic choice. A later call with a different explicit variant switches Mitsuba's variant.
    """
    global _backend
    variant = variant or os.environ.get(ENV_VARIANT) or None
    if _backend is not None:
        if variant and variant != _backend.variant:
            _backend.mi.set_variant(variant)
            _backend = dataclasses.replace(_backend, variant=variant)
        if threads and threads != _backend.threads:
            _backend.dr.set_thread_count(threads)
            _backend = dataclasses.replace(_backend, threads=threads)
        return _backend

    llvm_path, llvm_error = None, None
    try:
        llvm_path = find_libllvm()
    except BackendError as exc:
        llvm_error = exc
    if llvm_path is not None:
        if "drjit" in sys.modules and os.environ.get(ENV_LLVM) != str(llvm_path):
            print(f"ngp-mi: warning: drjit was imported before ngp_mi.backend; {ENV_LLVM} may be ignored",
                  file=sys.stderr)
        os.environ[ENV_LLVM] = str(llvm_path)

    mi, dr = _import_libraries()
    if variant is None:
        if _cuda_works(mi, dr):
            variant = "cuda_ad_rgb"
        elif dr.has_backend(dr.JitBackend.LLVM):
            variant = "llvm_ad_rgb"
        else:
            raise BackendError(f"No CUDA device and no LLVM backend for Dr.Jit. {llvm_error or INSTALL_HINT}")
    if variant not in mi.variants():
        raise BackendError(f"{ENV_VARIANT}={variant!r} is not a Mitsuba variant; choose one of {mi.variants()}")
    if variant.startswith("llvm") and not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError(f"Variant {variant} needs Dr.Jit's LLVM backend, which did not load. "
                           f"{llvm_error or INSTALL_HINT}")
    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        raise BackendError(f"Variant {variant} needs a working CUDA driver and device.")
    mi.set_variant(variant)

    if threads is None and os.environ.get(ENV_THREADS):
        try:
            threads = int(os.environ[ENV_THREADS])
        except ValueError:
            raise BackendError(f"{ENV_THREADS}={os.environ[ENV_THREADS]!r} is not an integer") from None
    if threads is not None:
        if threads < 1:
            raise BackendError(f"thread count must be >= 1, got {threads}")
        dr.set_thread_count(threads)
    _backend = Backend(mi=mi, dr=dr, variant=variant,
                       libllvm=llvm_path if variant.startswith("llvm") else None,
                       threads=dr.thread_count())
    return _backend


def mitsuba() -> ModuleType:
    """The ``mitsuba`` module, with the project's variant set."""
    return load().mi


def drjit() -> ModuleType:
    """The ``drjit`` module, initialised for the project's variant."""
    return load().dr


def versions() -> dict[str, str]:
    """Versions of the libraries the backend rests on."""
    b = load()
    return {"mitsuba": b.mi.__version__, "drjit": b.dr.__version__}


# --------------------------------------------------------------------------- JIT housekeeping

def jit_sync() -> None:
    """Wait for all queued Dr.Jit work (for timings: Dr.Jit evaluates lazily and asynchronously)."""
    if _backend is not None:
        _backend.dr.sync_thread()


def jit_cleanup() -> None:
    """Release what the JIT holds between tests: queued work, cached allocations, kernel history."""
    gc.collect()
    if _backend is None:
        return
    dr = _backend.dr
    dr.sync_thread()
    dr.kernel_history_clear()
    dr.flush_malloc_cache()


if __name__ == "__main__":  # used by scripts/ensure-libllvm.sh
    try:
        print(find_libllvm())
    except BackendError as error:
        print(error, file=sys.stderr)
        sys.exit(1)
