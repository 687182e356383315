"""Artifact store, input readers and file formats (all file I/O lives here)."""
