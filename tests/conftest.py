"""Root conftest: its presence (with tests/__init__.py) puts the repo root on sys.path under
pytest's default import mode, so tests share helpers (`from tests.drivers.fake_aravis import
...`) with plain `pytest`. The contract suites every backend runs live in `drivers.testing`."""
