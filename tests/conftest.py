"""Test-suite settings: hypothesis examples are derandomized so CI runs are repeatable."""

from hypothesis import settings

settings.register_profile("flyknot", derandomize=True, deadline=None)
settings.load_profile("flyknot")
