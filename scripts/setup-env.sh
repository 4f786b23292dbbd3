#!/usr/bin/env bash
# Set-up step 2 of 2: the project's virtual environment in .venv with ComReg and its test extras.
#
# PyTorch: on a CPU machine this installs torch==2.13.0 (CPU build). A GPU user creates .venv and
# installs the CUDA build of torch for their driver first (see README); this script keeps it.
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
if .venv/bin/python -c "import torch" >/dev/null 2>&1; then
  echo "Keeping the installed torch $(.venv/bin/python -c 'import torch; print(torch.__version__)')"
else
  .venv/bin/python -m pip install --quiet "torch==2.13.0"
fi
.venv/bin/python -m pip install --quiet -e ".[test]"
# Compile every kernel once (numba caches them beside the code: ~35 s here instead of in the
# first registration, bone detection, live session or volume).
.venv/bin/python -c "from comreg_core.registration.geometry.kernels import compile_kernels; compile_kernels(); from comreg_core.registration.judgement.uncertainty_kernels import compile_uncertainty_kernels; compile_uncertainty_kernels(); from comreg_core.live.igtl import crc64; crc64(b'ComReg')"
.venv/bin/comreg --version
