"""The application: command line, scenario runner, reports, gym env, viewer, benchmarks.

The only runtime package that imports every other one (``tests/test_boundary.py``).
"""
