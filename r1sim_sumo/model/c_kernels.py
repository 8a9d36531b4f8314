"""Small C kernels for CPU training, compiled at first use and loaded with ``ctypes``.

A :class:`CKernel` names one C source next to this file and declares its functions' argument types. At first use
the source is compiled with the system C compiler (``$CC``, else ``cc`` / ``gcc``; ``-O3 -march=native -fopenmp``,
then without ``-march=native``, then without OpenMP where those fail) into ``~/.cache/r1sim_sumo/kernels/``
(``R1SIM_KERNEL_CACHE`` overrides it), keyed by the source, the flags, the compiler and the CPU, built aside and
moved into place (no half-written library). Where no compiler is found or every build fails the kernel is
unavailable with the reason in :meth:`CKernel.unavailable_reason`, and callers use their plain PyTorch path.
Each kernel has an environment switch (``NAME=0`` turns it off) so that a user can compare or rule it out.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

from torch import Tensor

FLAGS = ["-O3", "-march=native", "-fopenmp", "-fPIC", "-shared", "-std=c99"]
FALLBACK_FLAGS = (["-O3", "-fopenmp", "-fPIC", "-shared", "-std=c99"],  # compilers without -march=native
                  ["-O3", "-fPIC", "-shared", "-std=c99"])  # without OpenMP: one thread, same values


def _cpu_key() -> str:
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        return next((ln for ln in lines if ln.startswith("flags")), "") + next((ln for ln in lines if ln.startswith("model name")), "")
    except OSError:
        return platform.processor()


def pointer(t: Tensor | None) -> ctypes.c_void_p:
    """The data pointer of a (contiguous) tensor for a kernel argument; ``None`` gives NULL."""
    return ctypes.c_void_p(None if t is None else t.data_ptr())


class CKernel:
    """One C source (``source``, a file name next to this module) built once per process on first use.

    :param declare: sets ``argtypes`` / ``restype`` of the library's functions.
    :param switch: environment variable that turns the kernel off when set to ``0``.
    """

    def __init__(self, source: str, declare: Callable[[ctypes.CDLL], None], switch: str) -> None:
        self.source = Path(__file__).with_name(source)
        self.declare, self.switch = declare, switch
        self._lock = threading.Lock()
        self._lib: ctypes.CDLL | None = None
        self._error: str | None = None

    def _build(self) -> ctypes.CDLL:
        cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        if not cc:
            raise RuntimeError("no C compiler (cc / gcc) on PATH")
        src = self.source.read_bytes()
        cache = Path(os.environ.get("R1SIM_KERNEL_CACHE") or Path.home() / ".cache" / "r1sim_sumo" / "kernels")
        errors = []
        for flags in (FLAGS, *FALLBACK_FLAGS):
            key = hashlib.sha256(src + " ".join(flags).encode() + cc.encode() + _cpu_key().encode()).hexdigest()[:16]
            lib = cache / f"{self.source.stem}_{key}.so"
            if lib.exists():
                break
            cache.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=cache) as tmp:
                out = Path(tmp) / lib.name
                res = subprocess.run([cc, *flags, str(self.source), "-o", str(out), "-lm"], capture_output=True, text=True)
                if res.returncode == 0:
                    os.replace(out, lib)
                    break
                errors.append(f"{cc} {' '.join(flags)}: {res.stderr.strip()[-300:]}")
        else:
            raise RuntimeError(f"could not build {self.source.name}: " + " | ".join(errors))
        dll = ctypes.CDLL(str(lib))
        self.declare(dll)
        return dll

    def library(self) -> ctypes.CDLL | None:
        """The loaded library (built now if needed), or ``None`` where it cannot be built."""
        if self._lib is None and self._error is None:
            with self._lock:
                if self._lib is None and self._error is None:
                    try:
                        self._lib = self._build()
                    except (OSError, RuntimeError) as exc:
                        self._error = str(exc)
        return self._lib

    def available(self) -> bool:
        """True when the library is built (or builds now) and not turned off by ``<switch>=0``."""
        if os.environ.get(self.switch, "1") == "0":
            return False
        return self.library() is not None

    def unavailable_reason(self) -> str | None:
        """Why :meth:`available` is False (``None`` when it is True)."""
        if os.environ.get(self.switch, "1") == "0":
            return f"turned off by {self.switch}=0"
        self.library()
        return self._error
