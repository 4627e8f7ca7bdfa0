"""atdrone: adaptive teaming in multi-drone pursuit (the AT-Drone benchmark as a service)."""

__version__ = "0.1.0"
