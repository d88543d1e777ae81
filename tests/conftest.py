"""Root conftest: its presence (with tests/__init__.py) puts the repo root on sys.path under
pytest's default import mode, so `from tests.contracts... import ...` works with plain `pytest`."""
