"""The one rerun boundary: the run recorder, its sinks, the viewer and the blueprint; nothing else imports rerun."""
