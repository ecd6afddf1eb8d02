"""leveler: real-time drag-free leveling of a tilting lab table."""

__version__ = "0.1.0"
