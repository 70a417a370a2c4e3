"""A tracking run: the loop over a source, its decode and output threads, and the outputs it writes.

- :mod:`.loop`: :func:`~.loop.run_session`, a run step by step (open, track every frame, close, summarise).
- :mod:`.options`: :class:`~.options.RunOptions`, how a run reads, logs and records beyond the tracker.
- :mod:`.run_outputs`: :class:`~.run_outputs.RunOutputs`, every output of a run and the order they close in.
- :mod:`.outputs`: the file writers (``poses.csv``, ``raw.mkv``, ``summary.json``) and the run's statistics.
- :mod:`.threads`: decoding ahead of the tracker, and drawing and logging behind it.
"""
