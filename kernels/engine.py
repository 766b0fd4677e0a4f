"""Which kernel engine runs the kernels, told without importing it.

Two engines run the same kernel source: Taichi, and quadrants, its maintained fork (wheels for newer Pythons).
Taichi is the default where it is installed, quadrants where it is not; ``TI_CMAX_ENGINE=taichi|quadrants`` chooses.
:mod:`.runtime` imports the chosen one; ``ti-cmax --version`` and report.json name it through :func:`engine_text`
(read from the installed distribution, so asking costs no engine import).
"""
from __future__ import annotations

import os

ENGINES = ("taichi", "quadrants")
ENV = "TI_CMAX_ENGINE"


def engine_name() -> str:
    """The engine's module name: ``TI_CMAX_ENGINE`` when set, else taichi where installed, else quadrants."""
    from importlib.util import find_spec

    chosen = os.environ.get(ENV, "").strip().lower()
    if chosen:
        if chosen not in ENGINES:
            from ti_cmax.errors import InputError

            raise InputError(f"{ENV}={os.environ[ENV]!r}: expected one of {', '.join(ENGINES)}")
        return chosen
    return "taichi" if find_spec("taichi") is not None else "quadrants"


def installed_engines() -> list[str]:
    """The engines installed here, in ENGINES order."""
    from importlib.util import find_spec

    return [name for name in ENGINES if find_spec(name) is not None]


def engine_version(name: str | None = None) -> str | None:
    """The installed version of engine ``name`` (default: the chosen one), None when it is not installed."""
    from importlib import metadata

    try:
        return metadata.version(name or engine_name())
    except metadata.PackageNotFoundError:
        return None


def engine_info() -> dict:
    """``{"name": ..., "version": ...}`` of the chosen engine, for report.json (version None: not installed)."""
    name = engine_name()
    return {"name": name, "version": engine_version(name)}


def engine_text() -> str:
    """``"<engine> <version>"``, e.g. ``"taichi 1.7.4"`` (``"quadrants not installed"`` when it is missing)."""
    info = engine_info()
    return f"{info['name']} {info['version'] or 'not installed'}"
