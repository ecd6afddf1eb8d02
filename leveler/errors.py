"""Exceptions shared across modules, kept free of heavy imports so the CLI starts fast."""


class LogError(Exception):
    """A log file cannot be written or read; the message names the file."""
