"""What a user needs around the tracker, one package per command: printable marker sheets
(``markers/``), camera calibration (``calibrate/``), the PnP textbook's experiments (``study/``), marker
maps learned from video (``map/``) and exports of a run (``export/``).

Each package keeps its model, its report and its command apart: a ``command`` module turns the
command line into calls of the model modules and writes what the report modules produce."""
