"""Moved to :mod:`comreg_core.register` (kept while the CLI moves)."""

from comreg_core.register.registrar import MIN_US_EXTENT_MM, Registrar, search_start  # noqa: F401
