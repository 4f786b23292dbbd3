"""A registration of the ComReg module made exactly as ``comreg register --out`` makes it.

The module registers through :func:`comreg_core.register.register_to_directory`, the function
behind ``comreg register``: the US points nodes and the CT bone model are written as files into
the registration's folder (``inputs/``: each points node as a ``.ply`` in LPS, with its beam
origins when the node keeps them; the CT model as ``ct_bone.vtk``, LPS), registered into the
same folder (``transform.tfm``, ``registered_us*.ply``, ``config.yaml``, ``result.json``) and
the panel shows what ``result.json`` holds (:func:`comreg_core.register.read_result`). So the
panel's transform, verdict, ``p_correct`` and advice are the command line's on the same input,
and any key the judge adds to ``result.json`` reaches the panel unchanged.

- :func:`registerIntoFolder`: inputs -> folder -> ``(RegistrationResult, record)``;
- :func:`saveResultFolder`: a copy of a registration's folder (inputs included) elsewhere, its
  paths moved with it, so ``comreg report`` reads it there;
- :func:`newRegistrationFolder`: a fresh numbered folder for the next registration.

Function names are camelCase, as in 3D Slicer modules.
"""

import logging
import shutil
import tempfile
from pathlib import Path

from comreg_core import runs
from comreg_core.errors import ComRegError, OutputPlaceError
from comreg_core.io import PointCloud, write_points
from comreg_core.io._files import check_output_folder
from comreg_core.transforms import apply_transform, space_change
from comreg_plugin.bone_models import beamOriginsOfNode
from comreg_plugin.scene_inputs import arrayFromPointsNode, requirePointsNode
from comreg_plugin.scene_io import surfaceMeshFromModel

log = logging.getLogger(__name__)

#: The sub-folder of a registration folder holding the inputs the module wrote.
INPUTS_FOLDER = "inputs"
#: The CT bone model's file in :data:`INPUTS_FOLDER`.
CT_FILE = "ct_bone.vtk"
#: The files ``comreg register`` writes that name other files (their paths move on a copy).
RECORD_FILES = (runs.RESULT, runs.CONFIG)


def newRegistrationFolder(base) -> Path:
    """A new empty folder ``base/registration-NNN`` (the next free number); ``base`` is made
    if missing."""
    base = Path(base)
    base.mkdir(parents=True, exist_ok=True)
    k = 1
    while (base / f"registration-{k:03d}").exists():
        k += 1
    folder = base / f"registration-{k:03d}"
    folder.mkdir()
    return folder


def temporaryBase() -> Path:
    """A folder for the registrations of a scene not saved yet (in the system's temporary
    folder; 3D Slicer's own temporary path inside the application)."""
    return Path(tempfile.mkdtemp(prefix="ComReg-"))


def exportInputs(folder: Path, usNodes: list, ctModelNode) -> tuple:
    """Write the US points nodes (their own frame, LPS, with beam origins when kept) and the CT
    bone model (LPS) into ``folder/inputs``; returns ``(points paths, CT path or None)``."""
    inputs = Path(folder) / INPUTS_FOLDER
    inputs.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, node in enumerate(usNodes, start=1):
        requirePointsNode(node)
        points = apply_transform(space_change("RAS", "LPS"), arrayFromPointsNode(node))
        name = "us_points.ply" if len(usNodes) == 1 else f"us_points_{k}.ply"
        paths.append(write_points(PointCloud(points, "LPS",
                                             beam_origins=beamOriginsOfNode(node, "LPS")),
                                  inputs / name))
    ctPath = None
    if ctModelNode is not None:
        from comreg_core.io.meshes import write_mesh

        ctPath = write_mesh(surfaceMeshFromModel(ctModelNode), inputs / CT_FILE)
    return paths, ctPath


def registerIntoFolder(folder: Path, usNodes: list, registrar, *, runDirectory, ctModelNode,
                       seed: int, device: str, prior=None, calibration=None) -> tuple:
    """Register ``usNodes`` (one body, as ``comreg register A B``) with ``registrar`` (the
    search on ``ctModelNode``, or the run ``runDirectory``'s network and search) into
    ``folder`` by :func:`~comreg_core.register.register_to_directory`; ``calibration``: the
    verdict's calibration file (default: the run's own). Returns ``(RegistrationResult,
    record)``, the record being ``result.json`` as read back."""
    from comreg_core.register import read_result, register_to_directory

    folder = Path(folder).resolve()
    paths, ctPath = exportInputs(folder, usNodes, ctModelNode if runDirectory is None
                                 else None)
    result = register_to_directory(
        runDirectory, paths[0] if len(paths) == 1 else paths, folder, device=device,
        seed=seed, ct_mesh=ctPath, calibration=calibration, prior=prior, registrar=registrar)
    return result, read_result(folder)


def saveResultFolder(source, target) -> Path:
    """Copy the registration folder ``source`` (``comreg register``'s files and the inputs)
    into ``target`` (made if missing; files of the same names replaced) and move the paths
    ``result.json`` and ``config.yaml`` give inside ``source`` to ``target``. Returns
    ``target``."""
    source, target = Path(source), Path(target)
    if not (source / runs.RESULT).is_file():
        raise ComRegError(f"'{source}' holds no registration result.", "Register first.")
    target = check_output_folder(target, inputs=[source], what="result folder")
    if source.resolve() in (target.resolve(), *target.resolve().parents):
        raise OutputPlaceError(f"The result folder '{target}' is inside the registration's "
                               f"own folder '{source}'.", "Choose a folder outside it.")
    staging = Path(tempfile.mkdtemp(prefix=".comreg-save-", dir=_existingParent(target)))
    try:
        shutil.copytree(source, staging, dirs_exist_ok=True)
        for name in RECORD_FILES:
            _relocateFile(staging / name, str(source.resolve()), str(target.resolve()))
        target.mkdir(parents=True, exist_ok=True)
        for item in sorted(staging.rglob("*")):  # each file renamed into place
            destination = target / item.relative_to(staging)
            if item.is_dir():
                destination.mkdir(exist_ok=True)
            else:
                item.replace(destination)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    log.info("Saved the registration folder '%s' as '%s'", source, target)
    return target


def _existingParent(path: Path) -> Path:
    path = path.absolute()
    while not path.exists():
        path = path.parent
    return path if path.is_dir() else path.parent


def _relocateFile(path: Path, old: str, new: str) -> None:
    """Rewrite ``path`` (``result.json`` or ``config.yaml``) with each string path under
    ``old`` moved under ``new``, written as ``comreg register`` writes the file."""
    if not path.is_file():
        return
    if path.suffix == ".json":
        from comreg_core.io.json_files import read_json, write_json

        write_json(relocate(read_json(path), old, new), path)
    else:
        import yaml

        text = yaml.safe_dump(relocate(yaml.safe_load(path.read_text(encoding="utf-8")), old,
                                       new), sort_keys=False)
        path.write_text(text, encoding="utf-8")


def relocate(value, old: str, new: str):
    """``value`` (JSON-like) with every string equal to ``old`` or starting with ``old/``
    starting with ``new`` instead."""
    if isinstance(value, dict):
        return {key: relocate(item, old, new) for key, item in value.items()}
    if isinstance(value, list):
        return [relocate(item, old, new) for item in value]
    if isinstance(value, str) and (value == old or value.startswith(old.rstrip("/") + "/")):
        return new + value[len(old):]
    return value
