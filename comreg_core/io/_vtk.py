"""Running VTK readers and writers so their errors become typed ComReg errors, not stderr noise."""

from __future__ import annotations

import re
from pathlib import Path

from comreg_core.errors import ComRegError, CorruptFileError


def run_vtk(algorithm, path: str | Path, *, writing: bool = False) -> None:
    """Run a VTK reader/writer, turning VTK error events into :class:`CorruptFileError` (reading)
    or :class:`ComRegError` (writing). Warnings are collected the same way and ignored."""
    messages: list[str] = []

    def on_error(_obj, _event, *args):  # VTK passes the message as call data when it can
        messages.append(str(args[0]) if args else "VTK reported an error")

    on_error.CallDataType = "string0"  # ask VTK to hand over the message text
    import vtk

    error_tag = algorithm.AddObserver("ErrorEvent", on_error)
    warning_tag = algorithm.AddObserver("WarningEvent", lambda *a: None)
    previous_window = vtk.vtkOutputWindow.GetInstance()
    previous_window.Register(None)  # keep it alive while it is not the instance
    captured = vtk.vtkStringOutputWindow()  # pipeline/parser errors would go to stderr
    vtk.vtkOutputWindow.SetInstance(captured)
    stderr_verbosity = vtk.vtkLogger.GetCurrentVerbosityCutoff()  # stderr is the only sink
    vtk.vtkLogger.SetStderrVerbosity(vtk.vtkLogger.VERBOSITY_OFF)
    try:
        if writing:
            ok = algorithm.Write()
        else:
            algorithm.Update()
            ok = 1
    finally:
        vtk.vtkLogger.SetStderrVerbosity(stderr_verbosity)
        vtk.vtkOutputWindow.SetInstance(previous_window)
        previous_window.UnRegister(None)
        algorithm.RemoveObserver(error_tag)
        algorithm.RemoveObserver(warning_tag)
    if messages or ok != 1 or "ERROR" in captured.GetOutput():
        detail = _clean([*messages, captured.GetOutput()])
        if writing:
            raise ComRegError(f"Could not write '{path}': {detail}.",
                              "Check that the folder is writable and the disk is not full.")
        raise CorruptFileError(path, detail)


#: VTK's generic follow-up errors, which say nothing about the file.
_PIPELINE_NOISE = ("returned failure for request", "vtkInformation")


def _clean(texts: list[str]) -> str:
    """The first informative VTK message in ``texts``, without the ``ERROR: In file, line n``
    and ``vtkClass (0x...):`` prefixes, object addresses, pipeline follow-ups and trailing
    dots."""
    for text in texts:
        for part in re.split(r"(?:ERROR|Warning): In \S+, line \d+\s*", " ".join(text.split())):
            part = re.sub(r"^\w+ \(0x[0-9a-fA-F]+\): ", "", part.strip())
            part = re.sub(r"\s*\(0x[0-9a-fA-F]+\)", "", part).strip().rstrip(". ")
            if part and not any(noise in part for noise in _PIPELINE_NOISE):
                return part
    return "VTK could not process it"
