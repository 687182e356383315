"""Prefect tasks: one thin, cached adapter per pipeline stage."""
