import os
import tempfile

import numpy as np
import pytest
import trimesh

from comreg_core.registration.geometry.surface import CTSurface
from tests.helpers import BOX_CENTRE, BOX_HALF, FIBULA_STL, SHARED_DATA

os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")


@pytest.fixture(scope="session", autouse=True)
def system_temporary_folder(tmp_path_factory):
    """The system's temporary folder, for this process and the processes it starts, is one in
    pytest's own folder (which pytest prunes): what the code under test puts there (the
    module's registrations of an unsaved scene, torchrun's rendezvous files) is not left in
    /tmp (each run of the suite left about 20 such folders there)."""
    folder = str(tmp_path_factory.mktemp("system-tmp"))
    with pytest.MonkeyPatch.context() as patch:  # both put back after the run
        patch.setenv("TMPDIR", folder)
        patch.setattr(tempfile, "tempdir", folder)
        yield folder


@pytest.fixture(scope="session")
def shared_data():
    """Path to ../shared/data; the real recorded data every test run must have."""
    if not SHARED_DATA.is_dir():
        pytest.fail(f"Real test data not found at {SHARED_DATA}: clone the project beside shared/.")
    return SHARED_DATA


# --- CT surfaces: a box with analytic distances, and the real fibula ---

@pytest.fixture(scope="session")
def box_mesh():
    """A closed box 40 x 20 x 10 mm centred at BOX_CENTRE (12 triangles)."""
    mesh = trimesh.creation.box(extents=2 * BOX_HALF)
    mesh.apply_translation(BOX_CENTRE)
    return mesh


@pytest.fixture(scope="session")
def box_surface(box_mesh):
    return CTSurface(box_mesh)


@pytest.fixture(scope="session")
def box_cloud():
    """300 points on the top face (z = max) and 200 on the +x face of the box."""
    rng = np.random.default_rng(7)
    top = BOX_CENTRE + np.column_stack([rng.uniform(-20, 20, 300), rng.uniform(-10, 10, 300),
                                        np.full(300, 5.0)])
    side = BOX_CENTRE + np.column_stack([np.full(200, 20.0), rng.uniform(-10, 10, 200),
                                         rng.uniform(-5, 5, 200)])
    return np.vstack([top, side])


@pytest.fixture(scope="session")
def fibula_surface(shared_data):
    return CTSurface(FIBULA_STL)


@pytest.fixture(scope="session")
def fibula_patch(fibula_surface):
    """A partial patch of the fibula like a US view: the 20,000 of 100,000 fresh area-uniform
    surface samples (a seed other than the surface's) nearest a viewpoint 60 mm beside the bone
    near one end (40% of the length from the centre along the long axis)."""
    from comreg_core.simulation import BoneModel

    bone = BoneModel(FIBULA_STL)
    points, _ = CTSurface(FIBULA_STL, sample_seed=99).samples(100_000)
    view = bone.centre + 0.4 * bone.length * bone.axes[:, 0] + 60.0 * bone.axes[:, 1]
    return points[np.argsort(np.linalg.norm(points - view, axis=1))[:20_000]]
