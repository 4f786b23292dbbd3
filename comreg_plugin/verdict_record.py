"""What the ComReg panel shows of a registration, read from its record alone.

The record is ``comreg register``'s ``result.json`` (:mod:`comreg_plugin.result_folder`), or a
live update's figures. :func:`recordFigures` picks the figures the panel and the transform node
carry (the verdict and its reasons, ``p_correct``, the confidence, the advice, the uncertainty
and where to scan next when the record has them, the competitor, the run's warnings);
:func:`describeFigures` writes them as the panel's lines; :func:`setFigureAttributes` /
:func:`figuresFromNode` store them on a node as ``ComReg.*`` attributes (strings, saved with
the scene) and read them back.
Whatever the record adds under ``uncertainty`` or ``scan_next`` is shown as it is.

Function names are camelCase, as in 3D Slicer modules.
"""

import json
from typing import Optional

from comreg_plugin.bone_models import ATTRIBUTE_PREFIX

#: The figures a registration leaves on its transform node (``ComReg.<name>``); JSON values
#: (lists, dicts) are stored as JSON text, numbers with every digit, absent ones as "".
FIGURE_NAMES = ("verdict", "verdict_reasons", "p_correct", "confidence", "ambiguous", "advice",
                "uncertainty", "uncertainty_mm", "scan_next", "competitor", "warnings",
                "result_folder")
#: Figures stored as JSON text.
JSON_FIGURES = ("verdict_reasons", "uncertainty", "scan_next", "competitor", "warnings")
#: Figures that are lists (empty when absent).
LIST_FIGURES = ("verdict_reasons", "warnings")


def recordAdvice(record: dict) -> str:
    """The advice of a record: its own ``advice`` (text), else, when the verdict is CHECK, the
    words of ``scan_next`` (where to scan to shrink the pose's bound), else the pose search's
    ambiguity advice (``search.advice.advice``; ``hypotheses`` in older records); "" if
    none."""
    advice = record.get("advice")
    if isinstance(advice, dict):
        advice = advice.get("advice") or advice.get("words")
    if not advice and record.get("verdict") != "ok":
        advice = (record.get("scan_next") or {}).get("words")
    if not advice:
        search = record.get("search") or record.get("hypotheses") or {}
        advice = (search.get("advice") or {}).get("advice")
    return str(advice or "")


def recordFigures(record: dict, resultFolder: Optional[str] = None) -> dict:
    """The figures of a ``result.json`` record (names of :data:`FIGURE_NAMES`, values as the
    record has them; None where it has none)."""
    search = record.get("search") or record.get("hypotheses") or {}  # older records: hypotheses
    uncertainty = record.get("uncertainty")
    competitor = record.get("competitor")
    if competitor is not None and competitor.get("name") is None:
        competitor = None  # the search found no clinically different pose
    return {"verdict": record.get("verdict"),
            "verdict_reasons": list(record.get("verdict_reasons") or []),
            "p_correct": record.get("p_correct"),
            "confidence": record.get("confidence", search.get("confidence")),
            "ambiguous": record.get("ambiguous", search.get("ambiguous")),
            "advice": recordAdvice(record) or None,
            "uncertainty": uncertainty,
            "uncertainty_mm": (uncertainty or {}).get("bound_mm"),
            "scan_next": record.get("scan_next"),
            "competitor": competitor,
            "warnings": list(record.get("warnings") or []),
            "result_folder": resultFolder}


def _weakest(uncertainty: dict) -> Optional[dict]:
    """The direction of largest bound in ``uncertainty["directions"]``, or None."""
    directions = [d for d in uncertainty.get("directions") or [] if isinstance(d, dict)]
    if not directions:
        return None
    return max(directions, key=lambda d: (d.get("bound_mm") or 0.0, d.get("bound_deg") or 0.0))


def describeFigures(figures: dict) -> list:
    """The panel's lines for ``figures`` (:func:`recordFigures`): the verdict, each reason,
    each of the run's warnings, ``p_correct`` and the confidence, the uncertainty (95 % bound,
    weakest direction), the competitor, the advice and where to scan next."""
    verdict = figures.get("verdict")
    lines = [f"Verdict: {verdict.upper()}" if verdict else "Verdict: none (this method is "
             "not judged)"]
    lines += [f"  - {reason}" for reason in figures.get("verdict_reasons") or []]
    lines += [f"Warning: {warning}" for warning in figures.get("warnings") or []]
    numbers = []
    if figures.get("p_correct") is not None:
        numbers.append(f"p_correct {float(figures['p_correct']):.2f}")
    if figures.get("confidence") is not None:
        numbers.append(f"confidence {float(figures['confidence']):.2f}")
    if figures.get("ambiguous"):
        from comreg_core.registration.judgement.verdict import (ambiguity_words,
                                                                competitor_ruled_out)

        competitor = (figures.get("uncertainty") or {}).get("competitor")
        numbers.append(f"another pose scored {ambiguity_words(True, competitor)}"
                       if competitor_ruled_out(competitor)
                       else "AMBIGUOUS: another pose fits about as well")
    if numbers:
        lines.append(", ".join(numbers))
    uncertainty = figures.get("uncertainty") or {}
    if uncertainty.get("bound_mm") is not None:
        text = f"Uncertainty: 95 % within {float(uncertainty['bound_mm']):.1f} mm at the bone"
        weakest = _weakest(uncertainty)
        if weakest is not None:
            parts = [f"{float(weakest[k]):.1f} {unit}" for k, unit in
                     (("bound_mm", "mm"), ("bound_deg", "deg")) if weakest.get(k) is not None]
            text += f"; weakest {weakest.get('words', 'direction')}" + (
                f" ({', '.join(parts)})" if parts else "")
        lines.append(text)
    competitor = figures.get("competitor")
    if competitor and competitor.get("distance_mm") is not None:
        lines.append(f"Competing pose '{competitor.get('name')}': "
                     f"{float(competitor['distance_mm']):.0f} mm, "
                     f"{float(competitor.get('rotation_deg') or 0.0):.0f} deg away, margin "
                     f"{float(competitor.get('margin') or 0.0):.2f}")
    if figures.get("advice"):
        lines.append(f"Advice: {figures['advice']}")
    scan = figures.get("scan_next") or {}
    if scan.get("words") and scan.get("words") != figures.get("advice"):
        lines.append(f"Scan next: {scan['words']}")
    return lines


def _attributeText(name: str, value) -> str:
    if value is None:
        return ""
    if name in JSON_FIGURES:
        return json.dumps(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def setFigureAttributes(node, figures: dict, names=FIGURE_NAMES) -> None:
    """Store ``figures`` on ``node`` as ``ComReg.<name>`` attributes (every name of ``names``;
    "" where absent, so an earlier registration's value never lingers)."""
    for name in names:
        node.SetAttribute(ATTRIBUTE_PREFIX + name, _attributeText(name, figures.get(name)))


def figuresFromNode(node) -> dict:
    """The figures :func:`setFigureAttributes` stored on ``node`` (None where empty)."""
    figures = {}
    for name in FIGURE_NAMES:
        text = node.GetAttribute(ATTRIBUTE_PREFIX + name) or ""
        if not text:
            figures[name] = [] if name in LIST_FIGURES else None
        elif name in JSON_FIGURES:
            figures[name] = json.loads(text)
        elif name in ("p_correct", "confidence", "uncertainty_mm"):
            figures[name] = float(text)
        elif name == "ambiguous":
            figures[name] = text == "true"
        else:
            figures[name] = text
    return figures
