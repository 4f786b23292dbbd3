"""ComReg core library: CT-ultrasound bone surface registration via patient-specific shape completion.

No Slicer, no Qt. Data flows one way: io -> surfaces -> (simulation -> training) -> inference ->
evaluation/report. Conventions (README, "Conventions"): millimetres, radians inside, rigid transforms
as 4x4 float64 arrays named ``T_<to>_<from>`` with ``T_ct_us @ p_us = p_ct``.
"""

__version__ = "0.1.0"
