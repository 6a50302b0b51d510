"""Lazy package exports: a package's ``__init__`` names its public API in ``__all__`` and imports each name from its
module only when first used, so ``import planner.localize`` does not load CasADi, nor ``import robot.driver`` fem."""
from __future__ import annotations

import importlib


def lazy_exports(package: str, table: dict[str, str]):
    """``(__getattr__, __dir__)`` for a package whose public names come from ``table`` (name -> submodule)."""
    def __getattr__(name: str):
        try:
            module = table[name]
        except KeyError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        return getattr(importlib.import_module(f"{package}.{module}"), name)

    def __dir__():
        return sorted(table)
    return __getattr__, __dir__
