"""3D Slicer scripted module "ComReg" (Module, ParameterNode, Widget, Logic, Test).

The module's classes live in ``ComReg.py`` (added with the Slicer module issue); like the CLI it
only calls ``comreg_core`` functions.
"""
