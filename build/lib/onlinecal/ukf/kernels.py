"""Compiled (numba) kernels of the UKF's per-block work: the switch between them and the numpy reference,
and their compilation cache. The kernels themselves: :mod:`.kernels_propagate` (sigma points through a
block, sensor model, attitude errors) and :mod:`.kernels_update` (sigma points, moments, the update); their
names stay importable from here (``kernels.update_kernel``).

The numpy functions of :mod:`onlinecal.ukf.propagate`, :mod:`onlinecal.ukf.layout` and
:mod:`onlinecal.ukf.unscented` are the reference: every kernel computes the same quantity in the same
equations, written as loops over sigma points and samples so that one call does a whole block without going
back to the interpreter (the numpy path spends most of a block in dispatch overhead of dozens of small array
operations). Results agree with the reference to rounding (tests/test_speed_kernels.py: ≤ 1e-9 relative);
the order of the floating-point operations differs (a sequential product instead of the reference's
log₂-depth scan), so they are not bit-identical.

Backend: ``ONLINECAL_KERNELS=numba|numpy`` in the environment when this module is first imported, or
:func:`set_backend` at run time; ``numba`` is the default where numba imports, else ``numpy`` (another
value: a RuntimeWarning, and the default).

Compilation is cached on disk (``cache=True``). Numba writes its cache next to this file when the package
directory is writable and otherwise in a per-user directory; where neither is writable (a read-only
install, a sandbox without a home), ``NUMBA_CACHE_DIR`` is set here to ``$XDG_CACHE_HOME/onlinecal/numba``
or ``~/.cache/onlinecal/numba`` and, failing those, to a directory under the system's temporary directory,
before numba is imported. A user's own ``NUMBA_CACHE_DIR`` is left alone.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import tempfile
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

BACKENDS = ("numba", "numpy")


def _writable(d: Path) -> bool:
    """Whether files can be created in d (made if missing)."""
    try:
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=d):
            pass
        return True
    except OSError:
        return False


def _cache_dir() -> str | None:
    """The directory numba's cache should use, or None where numba's own default (next to this file)
    is writable. Only consulted when the user has not set ``NUMBA_CACHE_DIR``."""
    here = Path(__file__).resolve().parent / "__pycache__"
    if _writable(here):
        return None
    xdg = os.environ.get("XDG_CACHE_HOME")
    cands = [Path(xdg)] if xdg else []
    with contextlib.suppress(RuntimeError):
        cands.append(Path.home() / ".cache")
    cands.append(Path(tempfile.gettempdir()) / f"onlinecal-{os.getuid() if hasattr(os, 'getuid') else 'user'}")
    for c in cands:
        d = c / "onlinecal" / "numba"
        if _writable(d):
            return str(d)
    return None


if "NUMBA_CACHE_DIR" not in os.environ:
    _d = _cache_dir()
    if _d is not None:
        os.environ["NUMBA_CACHE_DIR"] = _d

try:
    import numba

    if "numba.core.config" in __import__("sys").modules:  # imported before us: re-read NUMBA_CACHE_DIR
        numba.core.config.reload_config()
    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is a dependency; the numpy path still works without it
    numba = None  # type: ignore[assignment]
    HAVE_NUMBA = False


def _njit(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``numba.njit(cache=True)`` (no parallelism: one core), or the plain function without numba.

    The GIL is kept (no ``nogil``): the kernels are short (tens of µs) and in ``onlinecal run`` a reader
    thread decodes the link; releasing and re-taking the GIL around every kernel call cost more CPU there
    than it saved (bench_live: 7.2 % of a core with nogil, 6.3 % without; the numpy path 6.9–7.3 %)."""
    if not HAVE_NUMBA:
        return fn
    return numba.njit(cache=True)(fn)


_default = "numba" if HAVE_NUMBA else "numpy"
_backend = os.environ.get("ONLINECAL_KERNELS", _default).strip().lower()
if _backend not in BACKENDS:
    # an environment variable is not worth a crash: say so in one line and run on the default
    warnings.warn(f"ONLINECAL_KERNELS={_backend!r} is not one of {', '.join(BACKENDS)}: using {_default}",
                  RuntimeWarning, stacklevel=1)
    _backend = _default
if _backend == "numba" and not HAVE_NUMBA:
    _backend = "numpy"


def backend() -> str:
    """The backend in use: "numba" (compiled kernels) or "numpy" (the reference)."""
    return _backend


def set_backend(name: str) -> str:
    """Switch the backend ("numba" or "numpy"); returns the previous one. "numba" without numba installed
    raises RuntimeError."""
    global _backend
    if name not in BACKENDS:
        raise ValueError(f"kernel backend {name!r}: expected one of {', '.join(BACKENDS)}")
    if name == "numba" and not HAVE_NUMBA:
        raise RuntimeError("kernel backend 'numba' requested but numba is not installed")
    old, _backend = _backend, name
    return old


@contextlib.contextmanager
def use_backend(name: str) -> Iterator[None]:
    """``with use_backend("numpy"): ...`` runs the block on that backend and restores the previous one."""
    old = set_backend(name)
    try:
        yield
    finally:
        set_backend(old)


# the kernels live in two modules by job; their names are read through this one as well (loaded on first use,
# so that this module, which they import for :func:`_njit`, never imports them while it is being loaded)
_KERNEL_MODULES = {
    "kernels_propagate": ("propagate_kernel", "propagate_numba", "model_pair_kernel", "rot_log_rel_kernel"),
    "kernels_update": ("cholesky_kernel", "sigma_points_kernel", "unscented_kernel", "innovation_kernel",
                       "gain_update_kernel", "update_kernel"),
}
_WHERE = {name: mod for mod, names in _KERNEL_MODULES.items() for name in names}


def __getattr__(name: str) -> Any:
    """A kernel of :mod:`.kernels_propagate` or :mod:`.kernels_update` by its name (PEP 562)."""
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__package__}.{_WHERE[name]}"), name)
