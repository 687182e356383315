"""Prefect flows: wiring of the stage tasks (single patient) and the command line."""
