"""The judgement of a registration: the OK/CHECK verdict from the files alone (with the prior's
reasons) and what the evidence is worth, ``p_correct`` and its per-patient calibration.
Imports ``geometry`` and ``search``.
"""
