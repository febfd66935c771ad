"""How the package's numba kernels are compiled: ``@njit(**JIT)``.

``cache``: compiled once per machine, then loaded from ``__pycache__``.

``error_model="numpy"``: numba's default ("python") model tests every float
division for a zero divisor, to raise ``ZeroDivisionError``, and that branch
keeps LLVM from vectorizing a loop that divides (measured 4x slower per
division in the Bellman kernel). No kernel here divides by zero, and IEEE
``inf``/``nan`` would be the right answer if one did.
"""

from __future__ import annotations

from typing import Literal, TypedDict


class JitOptions(TypedDict):
    """The keyword arguments of ``numba.njit`` used here, typed so ``njit(**JIT)`` type-checks."""

    cache: bool
    error_model: Literal["python", "numpy"]


JIT: JitOptions = {"cache": True, "error_model": "numpy"}
