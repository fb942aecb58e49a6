"""This process's Prefect settings for a child process (``streetcd run``'s supervised night)."""

from __future__ import annotations

from prefect.settings import get_current_settings


def prefect_environment() -> dict[str, str]:
    """The Prefect settings in force here, temporary ones included (a test's server), as
    environment variables: a child started with them talks to the same server."""
    return get_current_settings().to_environment_variables(exclude_unset=True)
