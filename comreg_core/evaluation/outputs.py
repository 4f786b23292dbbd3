"""What a registration method hands back to the evaluation harness."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from comreg_core.errors import ComRegError
from comreg_core.transforms import apply_transform, as_points, check_rigid, invert_rigid


@dataclass
class RegistrationOutput:
    """The result of registering one US cloud.

    Attributes:
        T_ct_us: ``(4, 4)`` float64 estimate mapping the cloud the method received into the CT
            frame (mm).
        runtime_s: seconds the method spent on this cloud (what the method itself counts as its
            registration time; one-off preparation of the CT is not included).
        completion: optional ``(M, 3)`` completed bone in the frame of the cloud the method
            received (the network's ``T_hat^t``), mm.
        info: method-specific extras (fitness values, iterations, ...), JSON-able.
        confidence: the method's own confidence in [0, 1], None if it gives none (ComReg's
            pose search: :mod:`comreg_core.registration.search.search`).
        ambiguous: whether the method flags its result as ambiguous, None if it cannot.
    """

    T_ct_us: np.ndarray
    runtime_s: float
    completion: np.ndarray | None = None
    info: dict[str, Any] = field(default_factory=dict)
    confidence: float | None = None
    ambiguous: bool | None = None


def as_registration_output(result: Any, wall_s: float) -> RegistrationOutput:
    """Normalise what a method returned.

    Accepted: a :class:`RegistrationOutput`; any object or mapping with ``T_ct_us`` and optionally
    ``runtime_s`` (else the measured ``wall_s``), ``completion`` (in the received cloud's frame)
    or ``completion_ct`` (in the CT frame under the method's own ``T_ct_us``; mapped back with its
    inverse), ``info``, ``confidence`` and ``ambiguous``; or a bare ``(4, 4)`` array (runtime =
    ``wall_s``).

    Raises:
        InvalidTransformError: ``T_ct_us`` is not a finite rigid 4x4 matrix.
        ComRegError: nothing usable was returned.
    """
    if isinstance(result, RegistrationOutput):
        get = lambda name: getattr(result, name, None)  # noqa: E731
    elif isinstance(result, Mapping):
        get = result.get
    elif isinstance(result, np.ndarray):
        get = {"T_ct_us": result}.get
    elif hasattr(result, "T_ct_us"):
        get = lambda name: getattr(result, name, None)  # noqa: E731
    else:
        raise ComRegError(
            f"A registration method returned a {type(result).__name__}, not a result.",
            "Return a RegistrationOutput, an object or dict with 'T_ct_us' (4x4) and "
            "'runtime_s', or a 4x4 array.")
    T = get("T_ct_us")
    if T is None:
        raise ComRegError("A registration method returned no 'T_ct_us'.",
                          "Return the estimated 4x4 T_ct_us.")
    T = check_rigid(T)
    runtime = get("runtime_s")
    runtime = float(wall_s if runtime is None else runtime)
    completion = get("completion")
    if completion is not None:
        completion = as_points(completion, "completion points")
    else:
        completion_ct = get("completion_ct")
        if completion_ct is not None:
            completion = apply_transform(invert_rigid(T),
                                         as_points(completion_ct, "completion points"))
    if completion is not None and len(completion) == 0:
        completion = None
    info = get("info") or {}
    confidence, ambiguous = get("confidence"), get("ambiguous")
    return RegistrationOutput(T, runtime, completion, dict(info),
                              None if confidence is None else float(confidence),
                              None if ambiguous is None else bool(ambiguous))
