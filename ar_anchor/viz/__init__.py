"""The one rerun boundary: nothing outside this package imports rerun.

- :mod:`.sinks`: :class:`~.sinks.Recording`, one rerun stream with its file and viewer sinks and the logging
  primitives the tools use (calibrate and study log through it).
- :mod:`.recorder`: :class:`~.recorder.RerunRecorder`, the tracker run's recording (its entity tree is there).
- :mod:`.blueprints`: the viewer layouts of a run, a calibration and a study.
- :mod:`.series`: time series kept per frame and sent in batches (the run's ``metrics/*``).
- :mod:`.parts`: shapes (a target's marker squares, an overlay model as a mesh) and entity names.
- :mod:`.viewer`: starting a local rerun viewer, or reusing the one already listening.
- :mod:`.screenshot`: a recording in the web viewer at one frame, as a PNG (headless Chromium, :mod:`.browser`).
"""
