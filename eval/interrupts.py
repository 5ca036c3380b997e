"""Ctrl-C inside compiled or simulator code.

SIGINT raises KeyboardInterrupt at the next Python bytecode; when that bytecode runs
inside a numba function's return (boxing its arrays) or a Drake callback, the
interrupt arrives wrapped: a SystemError ("returned a result with an exception set")
or a RuntimeError whose cause or context is the KeyboardInterrupt. `is_interrupt`
recognises both, so that an interrupted run stops as cleanly as a plain Ctrl-C.
"""
from __future__ import annotations


def is_interrupt(exc: BaseException | None) -> bool:
    """Whether `exc` is a KeyboardInterrupt or wraps one (its cause or context chain)."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
