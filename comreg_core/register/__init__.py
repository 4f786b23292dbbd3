"""Registering a US cloud to the CT, end to end: the :class:`Registrar` (the pose search, and
the pretrained network as an optional provider of further starts, imported only when a run is
loaded), the one judge of a result (:func:`judge`, :class:`Evidence`), the inputs besides the
points (priors, the verdict's calibration) and the result folder (:func:`register_to_directory`,
:func:`read_result`). Sits above ``training`` and below ``evaluation``, ``report`` and the CLI
(``docs/architecture.md``)."""

from comreg_core.register.folder import read_result, register_to_directory, summary_lines
from comreg_core.register.inputs import find_calibration, load_prior, parse_tolerance
from comreg_core.register.judge import Evidence, is_short_sweep, judge
from comreg_core.register.registrar import Registrar

__all__ = ["Evidence", "Registrar", "find_calibration", "is_short_sweep", "judge",
           "load_prior", "parse_tolerance", "read_result", "register_to_directory",
           "summary_lines"]
