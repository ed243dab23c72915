"""A package, so that its conftest.py is imported as ``report.conftest``: a second top-level ``conftest`` module
would replace tests/conftest.py, which other test modules import by that name."""
