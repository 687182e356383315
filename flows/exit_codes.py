"""The commands' exit codes, in one place.

Read by the command line (:mod:`tumor3d.flows.cli.errors`, which maps errors to them)
and by the cohort's result (:attr:`tumor3d.flows.cohort.CohortResult.exit_code`);
imports nothing, so the command line loads it without Prefect.
"""

from __future__ import annotations

__all__ = ["EXIT_CHECK", "EXIT_ENVIRONMENT", "EXIT_INPUT", "EXIT_INTERRUPTED", "EXIT_TERMINATED"]

#: Exit code of bad input (a file, option, configuration or manifest the user gave).
EXIT_INPUT = 2
#: Exit code of environment errors: store or output not writable, server unavailable,
#: a cohort patient failed for the machine (a full disk), not its input.
EXIT_ENVIRONMENT = 3
#: Exit code of results published with status ``check`` (a human should look).
EXIT_CHECK = 4
#: Exit code of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130
#: Exit code of a command stopped by SIGTERM (128 + 15: ``timeout``, systemd, Kubernetes).
EXIT_TERMINATED = 143
