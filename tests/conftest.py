"""Shared by every test file: ``tests/`` is on ``sys.path`` (pytest's rootdir import mode puts a
conftest's folder there), so a test anywhere below imports :mod:`budgets`, the training budgets
the tests share, and :mod:`public_names`."""
