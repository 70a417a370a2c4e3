"""The `ar-anchor` command line: parser, shared options, one function per command; flags in,
typed calls out, errors to exit codes."""
