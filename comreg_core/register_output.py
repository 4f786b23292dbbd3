"""Moved to :mod:`comreg_core.register` (kept while the CLI moves)."""

from comreg_core.register.folder import (read_result, register_to_directory,  # noqa: F401
                                         registration_verdict, summary_lines)
from comreg_core.register.inputs import (calibration_path, find_calibration,  # noqa: F401
                                         input_paths, join_clouds, load_prior, parse_tolerance,
                                         prior_inputs, prior_lines, register_inputs)
