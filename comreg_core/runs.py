"""File names of the folders ComReg writes: one home for each name.

A **run folder** (``comreg pretrain``) holds the trained network and how it was made; a
**registration folder** (``comreg register``, the demo's ``registration/``) holds one
registration, its evaluation and report. Both are described in the README.
"""

from __future__ import annotations

# --- the run folder of a pretraining ---------------------------------------------------------------
#: The checkpoint (weights, config YAML, CT mesh and fingerprint, normalisation, validation).
CHECKPOINT = "checkpoint.pt"
#: The CT mesh's fingerprint (sha256 of its geometry), checked when the run is loaded.
FINGERPRINT = "ct_fingerprint.json"
#: Everything needed to reproduce the run (seed included); also written beside registrations.
CONFIG = "config.yaml"
#: One row per epoch: losses, learning rate, validation figures.
TRAINING_LOG = "training_log.csv"
#: What makes a folder a run folder (only ``pretrain`` writes into one).
RUN_FOLDER_MARKERS = (CHECKPOINT, FINGERPRINT)

# --- the folder of a registration ----------------------------------------------------------------
#: ``T_ct_us`` and everything about the registration (verdict, timings, paths).
RESULT = "result.json"
#: ``T_ct_us`` as an ITK transform (LPS, Slicer's convention).
TRANSFORM = "transform.tfm"
#: The US points moved into the CT frame.
REGISTERED_US = "registered_us.ply"
#: With several US inputs, the k-th one's points (k = 1, 2, ...) moved into the CT frame.
REGISTERED_US_INPUT = "registered_us_{}.ply"
#: The per-patient calibration of ``p_correct`` (``comreg calibrate``, ``pretrain``).
CALIBRATION = "calibration.json"
#: The network's completed bone in the CT frame.
COMPLETION_CT = "completion_ct.ply"
#: An evaluation's trials and summary (``comreg evaluate``, the demo).
METRICS = "metrics.json"
#: The HTML report (``comreg report``) and its pictures' folder.
REPORT = "report.html"
