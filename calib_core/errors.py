"""Errors that carry a one-line message meant for the operator."""


class LasercalError(Exception):
    """Base of every error the CLI reports as a single ``error:`` line (exit status 2)."""


class InputError(LasercalError, ValueError):
    """Bad input data: unreadable file, missing column, non-finite value, too few rows."""


class DesignError(InputError):
    """The pose design cannot identify some parameters (rank-deficient regressor)."""
