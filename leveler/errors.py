"""Exceptions shared across modules, kept free of heavy imports so the CLI starts fast."""


class LogError(Exception):
    """A log file cannot be written or read; the message names the file."""


class ControlError(Exception):
    """The control socket cannot be set up (path, permissions, another daemon)."""
