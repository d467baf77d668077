"""Importing Sionna RT with a working backend.

On a machine with a CUDA GPU, Mitsuba/Dr.Jit use it.  Otherwise the CPU (LLVM) backend needs an LLVM
shared library >= 15; the ``karellen-llvm-core`` wheel installs one under ``<venv>/lib``, and
``DRJIT_LIBLLVM_PATH`` must point at it before ``sionna.rt`` is imported (this machine's own
libLLVM-15 makes Dr.Jit abort on its first kernel).
"""

from __future__ import annotations

import glob
import os
import sys


def _find_libllvm() -> str | None:
    for prefix in (sys.prefix, sys.base_prefix):
        for pattern in ("libLLVM.so.2[0-9]*", "libLLVM-2[0-9].so", "libLLVM.so"):
            hits = sorted(glob.glob(os.path.join(prefix, "lib", pattern)))
            if hits:
                return hits[-1]
    return None


def configure_llvm() -> None:
    """Point Dr.Jit at the bundled LLVM unless the user already chose one (done on ``import graf.sim``)."""
    if "drjit" not in sys.modules and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        lib = _find_libllvm()
        if lib:
            os.environ["DRJIT_LIBLLVM_PATH"] = lib


def import_sionna_rt():
    """Return the ``sionna.rt`` module, configuring Dr.Jit's LLVM backend first when needed."""
    configure_llvm()
    try:
        import sionna.rt as rt  # lazy: seconds to load, and only after configure_llvm
    except ImportError as exc:
        raise ImportError(
            "graf-simulate needs Sionna RT: install the project with its 'sim' extra "
            "(pip install -e '.[sim]', done by scripts/setup.sh)"
        ) from exc
    return rt
