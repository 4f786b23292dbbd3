"""Render resources/panel_3d.png, the 3D Slicer panel's 3D view after a registration, off-screen
from the headless scene (the README's and docs/guide.md's screenshot).

The bundled sample (CT segmentation, tracked sweep) is registered by the module's Logic with the
pose search, as the panel's *Register* does; the picture shows the CT bone model (translucent),
the US points coloured by their distance to the CT (with the legend), the competing pose (faint)
and, when the record names one, the region to scan next. Run from the repository root:

    .venv/bin/python scripts/make_panel_screenshot.py [--out resources/panel_3d.png]
"""

import argparse
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    import sys

    sys.path.insert(0, str(ROOT))
    from comreg_plugin.logic import ComRegLogic
    from comreg_plugin.scene_snapshot import renderScene
    from comreg_plugin.testing import SAMPLE_SEGMENTATION, SAMPLE_SWEEP
    from comreg_plugin.verdict_record import describeFigures

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "resources" / "panel_3d.png")
    args = parser.parse_args()
    logic = ComRegLogic()
    logic.getParameterNode().resultDirectory = tempfile.mkdtemp(prefix="panel-screenshot-")
    _, models = logic.loadSegmentation(SAMPLE_SEGMENTATION)
    models[0].GetDisplayNode().SetOpacity(0.45)
    points, _ = logic.loadTrackedSweep(SAMPLE_SWEEP)
    points.GetDisplayNode().SetPointSize(4.0)
    summary = logic.register(points, "search", ctModelNode=models[0])
    path = renderScene(logic.scene, args.out, fitNode=models[0])
    print(f"wrote {path} ({path.stat().st_size // 1024} KB)")
    print("\n".join(describeFigures(summary.figures)))


if __name__ == "__main__":
    main()
