"""A tracking run: the loop over a source, its decode and output threads, and the outputs it
writes (poses.csv, summary, videos)."""
