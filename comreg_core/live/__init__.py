"""Live registration while scanning: an OpenIGTLink stream of tracked B-mode frames in, the
US -> CT transform, its verdict and where to scan next out (``comreg live``), and a recorded
sweep served as PLUS Server would (``comreg replay``). docs/live.md describes both.

- :mod:`~comreg_core.live.stream`: frames, pairing images with poses, the probe calibration;
- :mod:`~comreg_core.live.intake`: which frames are used: skipped when they show no new bone,
  dropped when they waited too long;
- :mod:`~comreg_core.live.points`: a frame's bone points (``extract-us``'s detector), the
  growing sweep's points cleaned up incrementally, and the bone they cover;
- :mod:`~comreg_core.live.detection`, :mod:`~comreg_core.live.pipeline`: bone detection in
  worker processes, fed by a thread of its own, so that the update loop only registers;
- :mod:`~comreg_core.live.session`: the update loop's state: warm or full registration, the
  verdict (:mod:`~comreg_core.live.gates`: the live checks on top of the one judge), the
  advice;
- :mod:`~comreg_core.live.background`: the full search in a second process, so that warm
  updates go on while it runs;
- :mod:`~comreg_core.live.updates`: an update's record, ``updates.csv`` and ``frames.csv``;
- :mod:`~comreg_core.live.igtl`: reading OpenIGTLink messages and the live client (pyigtl);
- :mod:`~comreg_core.live.replay`: ``comreg replay``'s server;
- :mod:`~comreg_core.live.receiver`: the receiver thread (frames in, updates sent back);
- :mod:`~comreg_core.live.run`: the update loop and the output folder.

It sits at the top of comreg_core beside the CLI and the demo: it registers
(:mod:`comreg_core.register`), writes ``comreg register``'s folder
(:mod:`comreg_core.register.folder`) and its report (:mod:`comreg_core.report`).
"""
